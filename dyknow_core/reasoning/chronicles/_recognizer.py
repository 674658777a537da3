"""Chronicles: patterns of events with metric constraints, recognized online and incrementally.

A chronicle is a set of named events (each an input event kind with parameters and an
optional ``from``/``to`` value change), metric constraints ``lo <= t(end) - t(start) <= hi``
between their times (a simple temporal network), and optionally forbidden events in an
interval. Its definition (``ChronicleSpec``, pydantic, seconds) is checked and compiled
once (``compile_chronicle``: Floyd–Warshall on the distance graph; a negative cycle is a
``ChronicleError`` naming the constraints on it) into the form the hot path reads.

Recognition (``ChronicleRecognizer``) reports every occurrence: every assignment of
distinct input events to the chronicle's events that unifies the parameters, meets all
constraints and has no forbidden event in a forbidden interval. Events must come in
non-decreasing time (their valid time is the clock); an earlier one is counted as late and
ignored. Partial instances are indexed by (expected event, bound parameters), expire as
soon as one of their missing events can no longer come in time, and are capped in number
(the oldest dropped and counted). Because the minimal network of an STN is decomposable,
keeping each missing event's time window, narrowed from the assigned events only, is exact.

Forbidden intervals are open: ``between`` two events ``(t(start), t(end))``, or ``after``
one event ``(t(start) + lo, t(start) + hi)`` with ``0 <= lo``. A forbidden event's
parameters are either bound by its start event or free (any value).
"""

from __future__ import annotations

import heapq
import re
from collections import OrderedDict
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from ._events import ChangeEvent
from ._exceptions import DyKnowError, ProcessError
from ._policy import Order, Policy
from ._process import Process
from ._sample import RawSample
from ._stream import StreamGenerator, Subscription
from ._time import seconds_to_ns

if TYPE_CHECKING:
    from ._instance import DyKnowInstance

_INF = 1 << 62
_NEG_INF = -(1 << 62)


class ChronicleError(DyKnowError, ValueError):
    """A chronicle definition that is invalid or inconsistent; ``field`` names where."""

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        self.reason = message
        super().__init__(f"chronicle field {field!r}: {message}")


# -- definitions at the edge ---------------------------------------------------------------


def _as_arg_map(v: Any) -> Any:
    # a list of names is shorthand for "the chronicle parameter is the event argument"
    if isinstance(v, (list, tuple)):
        return {str(x): str(x) for x in v}
    return v


class EventSpec(BaseModel):
    """One event of a chronicle: an input kind, parameters, optionally a from→to change."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    name: str = Field(min_length=1)
    event: str = Field(min_length=1)
    args: dict[str, str] = Field(default_factory=dict)
    from_: Any = Field(default=None, alias="from")
    to: Any = None

    _norm_args = field_validator("args", mode="before")(_as_arg_map)


class ConstraintSpec(BaseModel):
    """``lo <= t(end) - t(start) <= hi`` in seconds; a missing bound is unbounded."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    start: str
    end: str
    lo: float | None = None
    hi: float | None = None


class ForbiddenSpec(BaseModel):
    """An event that must not occur in ``(t(start), t(end))`` or ``(t(start)+lo, t(start)+hi)``."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    event: str = Field(min_length=1)
    args: dict[str, str] = Field(default_factory=dict)
    from_: Any = Field(default=None, alias="from")
    to: Any = None
    start: str
    end: str | None = None
    lo: float | None = None
    hi: float | None = None

    _norm_args = field_validator("args", mode="before")(_as_arg_map)


class ChronicleSpec(BaseModel):
    """A chronicle definition: events, metric constraints, forbidden events, memory cap."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(min_length=1)
    events: list[EventSpec] = Field(min_length=1)
    constraints: list[ConstraintSpec] = Field(default_factory=list)
    forbidden: list[ForbiddenSpec] = Field(default_factory=list)
    max_partial: int = Field(default=10_000, gt=0)


# -- compiled form ------------------------------------------------------------------------


class _Node(NamedTuple):
    pos: int
    name: str
    kind: str
    has_from: bool
    from_: Any
    has_to: bool
    to: Any
    params: tuple[tuple[str, int], ...]  # (event argument, chronicle parameter index)


class _Forbid(NamedTuple):
    pos: int
    kind: str
    has_from: bool
    from_: Any
    has_to: bool
    to: Any
    params: tuple[tuple[str, int], ...]  # bound parameters only; free ones match anything
    start: int
    end: int  # -1: an ``after`` window
    lo: int
    hi: int


class CompiledChronicle:
    """A checked chronicle: nodes, the minimal distance matrix (ns), indexes by event kind."""

    def __init__(
        self,
        spec: ChronicleSpec,
        nodes: list[_Node],
        params: list[str],
        dist: list[list[int]],
        forbids: list[_Forbid],
    ) -> None:
        self.spec = spec
        self.name = spec.name
        self.nodes = nodes
        self.params = params
        self.dist = dist  # dist[i][j]: upper bound of t_j - t_i (ns); _INF when unbounded
        self.forbids = forbids
        self.max_partial = spec.max_partial
        self.kind_nodes: dict[str, list[_Node]] = {}
        for n in nodes:
            self.kind_nodes.setdefault(n.kind, []).append(n)
        self.kind_forbids: dict[str, list[_Forbid]] = {}
        for f in forbids:
            self.kind_forbids.setdefault(f.kind, []).append(f)
        self.kinds = frozenset(self.kind_nodes) | frozenset(self.kind_forbids)
        self.full = (1 << len(nodes)) - 1
        # what starting a partial instance at each event needs, computed once: relative to
        # its time its windows are row (upper) and negcol (lower), lists every instance
        # started there shares; it is dead at birth when another event must come first
        self.starts: list[tuple[bool, list[int], list[int], int]] = []
        for nd in nodes:
            i = nd.pos
            others = [dist[i][j] for j in range(len(nodes)) if j != i]
            mind = min(others) if others else _INF
            self.starts.append(
                (mind >= 0, dist[i][:], [-dist[j][i] for j in range(len(nodes))], mind)
            )

    def window(self, a: str, b: str) -> tuple[float | None, float | None]:
        """The implied bounds (seconds) of ``t(b) - t(a)`` in the minimal network."""
        ia = next(n.pos for n in self.nodes if n.name == a)
        ib = next(n.pos for n in self.nodes if n.name == b)
        hi = self.dist[ia][ib]
        lo = self.dist[ib][ia]
        return (
            None if lo >= _INF else -lo / 1e9,
            None if hi >= _INF else hi / 1e9,
        )


def _ns(x: float | None, default: int) -> int:
    return default if x is None else seconds_to_ns(x)


def _param_binding(
    args: Mapping[str, str], params: list[str], where: str
) -> tuple[tuple[str, int], ...]:
    out: list[tuple[str, int]] = []
    for p, arg in args.items():
        if not p.isidentifier():
            raise ChronicleError(f"{where}.args", f"parameter {p!r} is not an identifier")
        if p not in params:
            params.append(p)
        out.append((arg, params.index(p)))
    return tuple(out)


def compile_chronicle(definition: ChronicleSpec | Mapping[str, Any]) -> CompiledChronicle:
    """Validate a definition, check its temporal network is consistent, and compile it."""
    if isinstance(definition, ChronicleSpec):
        spec = definition
    else:
        try:
            spec = ChronicleSpec.model_validate(definition)
        except ValidationError as exc:
            err = exc.errors()[0]
            field = ".".join(str(x) for x in err["loc"]) or "definition"
            raise ChronicleError(field, err["msg"]) from None
    names: dict[str, int] = {}
    params: list[str] = []
    nodes: list[_Node] = []
    for i, ev in enumerate(spec.events):
        if ev.name in names:
            raise ChronicleError(f"events.{i}.name", f"event {ev.name!r} is defined twice")
        names[ev.name] = i
        fs = ev.model_fields_set
        nodes.append(
            _Node(
                i,
                ev.name,
                ev.event,
                "from_" in fs,
                ev.from_,
                "to" in fs,
                ev.to,
                _param_binding(ev.args, params, f"events.{i}"),
            )
        )
    n = len(nodes)

    def node(name: str, field: str) -> int:
        try:
            return names[name]
        except KeyError:
            raise ChronicleError(
                field, f"unknown event {name!r} (events: {', '.join(names)})"
            ) from None

    dist = [[_INF] * n for _ in range(n)]
    why: list[list[str | None]] = [[None] * n for _ in range(n)]
    for i in range(n):
        dist[i][i] = 0
    for k, c in enumerate(spec.constraints):
        a = node(c.start, f"constraints.{k}.start")
        b = node(c.end, f"constraints.{k}.end")
        if a == b:
            raise ChronicleError(f"constraints.{k}", "a constraint needs two different events")
        if c.lo is not None and c.hi is not None and c.lo > c.hi:
            raise ChronicleError(f"constraints.{k}", f"lo {c.lo} is greater than hi {c.hi}")
        text = f"{c.start} -> {c.end} [{c.lo}, {c.hi}]"
        if c.hi is not None and seconds_to_ns(c.hi) < dist[a][b]:
            dist[a][b] = seconds_to_ns(c.hi)
            why[a][b] = text
        if c.lo is not None and -seconds_to_ns(c.lo) < dist[b][a]:
            dist[b][a] = -seconds_to_ns(c.lo)
            why[b][a] = text
    _floyd_warshall(dist, why)

    forbids: list[_Forbid] = []
    for k, f in enumerate(spec.forbidden):
        where = f"forbidden.{k}"
        a = node(f.start, f"{where}.start")
        bound = {p for _, p in nodes[a].params}
        fparams: list[tuple[str, int]] = []
        for p, arg in f.args.items():
            if p in params:
                idx = params.index(p)
                if idx not in bound:
                    raise ChronicleError(
                        f"{where}.args",
                        f"parameter {p!r} must be bound by the start event {f.start!r} "
                        "or appear in no event (free)",
                    )
                fparams.append((arg, idx))
        if f.end is not None:
            b = node(f.end, f"{where}.end")
            if f.lo is not None or f.hi is not None:
                raise ChronicleError(f"{where}", "a window between two events takes no lo/hi")
            lo = hi = 0
        else:
            b = -1
            if f.hi is None:
                raise ChronicleError(f"{where}.hi", "an 'after' window needs hi (seconds)")
            lo = _ns(f.lo, 0)
            hi = seconds_to_ns(f.hi)
            if lo < 0:
                raise ChronicleError(f"{where}.lo", f"lo must be >= 0, got {f.lo}")
            if hi < lo:
                raise ChronicleError(f"{where}.hi", f"hi {f.hi} is less than lo {f.lo}")
        fs = f.model_fields_set
        forbids.append(
            _Forbid(
                k, f.event, "from_" in fs, f.from_, "to" in fs, f.to, tuple(fparams), a, b, lo, hi
            )
        )
    return CompiledChronicle(spec, nodes, params, dist, forbids)


def _floyd_warshall(dist: list[list[int]], why: list[list[str | None]]) -> None:
    """Tighten ``dist`` to all-pairs shortest paths; a negative cycle raises, naming it."""
    n = len(dist)
    nxt = [[j if dist[i][j] < _INF else -1 for j in range(n)] for i in range(n)]
    for k in range(n):
        dk = dist[k]
        for i in range(n):
            dik = dist[i][k]
            if dik >= _INF:
                continue
            di = dist[i]
            for j in range(n):
                if dk[j] >= _INF:
                    continue
                d = dik + dk[j]
                if d < di[j]:
                    di[j] = d
                    nxt[i][j] = nxt[i][k]
            if di[i] < 0:
                raise ChronicleError("constraints", _cycle_message(i, nxt, why))


def _cycle_message(i: int, nxt: list[list[int]], why: list[list[str | None]]) -> str:
    named: list[str] = []
    u = i
    for _ in range(len(nxt) + 1):
        v = nxt[u][i]
        if v < 0:
            break
        w = why[u][v]
        if w is not None and w not in named:
            named.append(w)
        u = v
        if u == i:
            break
    return "inconsistent temporal constraints (negative cycle): " + "; ".join(named)


# -- recognition ----------------------------------------------------------------------------


class Recognition(NamedTuple):
    """One recognized chronicle: its name, parameter bindings, and each event's time (ns)."""

    chronicle: str
    bindings: dict[str, Any]
    times: dict[str, int]


# A partial instance is a list, not an object: it is made and dropped once per matching
# event, and list literals and indexing are the cheapest Python has. Its slots:
# [seq, mask of assigned events, times, bindings, window lows, window highs, deadline,
#  where it is indexed, alive, origin]; ``times`` is the window-lows list itself (an
# assigned event's window is its time), never copied separately. Times and windows are
# relative to ``origin`` (the first assigned event's time), so a new instance shares the
# compiled start windows instead of building two lists per event: they are copied before
# any change. The deadline is absolute (the expiry heap orders by it).
_Partial = list


_UNBOUND: Any = object()
_new_tuple = tuple.__new__
_NO_ARGS: Mapping[str, Any] = {}
_NO_VALS: dict[int, Any] = {}  # never written: events without parameters share it


class RecognizerStats(NamedTuple):
    """Counters of a recognizer: events seen, recognitions, partial instances and losses."""

    events: int
    late: int
    recognized: int
    partial: int
    expired: int
    killed: int
    dropped: int


class ChronicleRecognizer:
    """Online, incremental recognition of one compiled chronicle over a stream of events."""

    def __init__(self, chronicle: CompiledChronicle | ChronicleSpec | Mapping[str, Any]) -> None:
        c = chronicle if isinstance(chronicle, CompiledChronicle) else compile_chronicle(chronicle)
        self.chronicle = c
        self.clock = _NEG_INF
        self._seq = 0
        self._alive: OrderedDict[int, _Partial] = OrderedDict()
        n = len(c.nodes)
        # per node: signature (bound parameter indexes) -> binding key -> partial instances
        self._index: list[dict[tuple[int, ...], dict[Any, dict[int, _Partial]]]] = [
            {} for _ in range(n)
        ]
        self._fidx: list[dict[Any, dict[int, _Partial]]] = [{} for _ in c.forbids]
        self._expiry: list[tuple[int, int, _Partial]] = []
        self._pending: list[tuple[int, int, _Partial]] = []
        self._missing: dict[tuple[int, int], list[tuple[int, int, int]]] = {}
        self._nparams = len(c.params)
        self._cap = c.max_partial
        self._names = [nd.name for nd in c.nodes]
        self._cname = c.name
        self._pnames = c.params
        self._no_binds: list[Any] = [_UNBOUND] * len(c.params)
        self._after = any(f.end < 0 for f in c.forbids)
        self._direct = -1 if self._after else c.full
        self._full = c.full
        # per input kind: its forbidden events, and per chronicle event what matching needs
        self._kinds: dict[str, tuple[list[_Forbid] | None, list[tuple[Any, ...]]]] = {}
        for kind in c.kinds:
            plan: list[tuple[Any, ...]] = []
            for nd in c.kind_nodes.get(kind, []):
                startable, row, negcol, mind = c.starts[nd.pos]
                plan.append(
                    (
                        nd.pos,
                        1 << nd.pos,
                        nd.has_from,
                        nd.from_,
                        nd.has_to,
                        nd.to,
                        nd.params,
                        self._index[nd.pos],
                        row,
                        startable,
                        negcol,
                        mind,
                        {},
                    )
                )
            self._kinds[kind] = (c.kind_forbids.get(kind), plan)
        self._plans: dict[int, list[tuple[tuple[int, ...], dict[Any, Any]]]] = {}
        self.events = self.late = self.recognized = 0
        self.expired = self.killed = self.dropped = 0

    # -- public ------------------------------------------------------------------------
    def stats(self) -> RecognizerStats:
        """The counters now (``partial`` is the live partial instances, pending included)."""
        return RecognizerStats(
            self.events,
            self.late,
            self.recognized,
            len(self._alive),
            self.expired,
            self.killed,
            self.dropped,
        )

    def advance(self, now: int) -> list[Recognition]:
        """Move the clock to ``now``: expire what can no longer complete, release the rest."""
        out: list[Recognition] = []
        if now > self.clock:
            self.clock = now
            self._expire(now)
            if self._pending:
                self._release(now, out)
        return out

    def feed(
        self,
        kind: str,
        time: int,
        args: Mapping[str, Any] | None = None,
        old: Any = None,
        new: Any = None,
    ) -> list[Recognition]:
        """One input event at ``time`` (ns); returns the recognitions it completes or releases."""
        out: list[Recognition] = []
        clock = self.clock
        if time > clock:
            self.clock = time
            heap = self._expiry
            if heap and heap[0][0] < time:
                # expire what can no longer complete (as _expire, inlined: nearly every
                # event lets some deadline pass)
                alive = self._alive
                pop = heapq.heappop
                gone = 0
                while heap and heap[0][0] < time:
                    deadline, seq, inst = pop(heap)
                    if inst[8] and inst[6] == deadline:
                        del alive[seq]
                        inst[8] = False
                        for parent, key in inst[7]:
                            bucket = parent[key]
                            del bucket[seq]
                            # an unkeyed table has one bucket: kept, as it soon refills
                            if not bucket and key:
                                del parent[key]
                        inst[7] = None
                        gone += 1
                self.expired += gone
            if self._pending:
                self._release(time, out)
        plan = self._kinds.get(kind)
        if plan is None:
            return out
        self.events += 1
        if time < clock:
            self.late += 1
            return out
        forbids, nodes = plan
        if args is None:
            args = _NO_ARGS
        if forbids is not None:
            self._forbidden(forbids, time, args, old, new)
        created: list[_Partial] = []
        # the full mask when a completion is reported at once, else no mask at all
        direct = self._direct
        for (
            i,
            bit,
            has_from,
            from_,
            has_to,
            to,
            params,
            index,
            di,
            startable,
            negcol,
            mind,
            missing,
        ) in nodes:
            if (has_from and old != from_) or (has_to and new != to):
                continue
            vals: dict[int, Any] = _NO_VALS
            if params:
                vals = {}
                ok = True
                for arg, p in params:
                    try:
                        v = args[arg]
                    except KeyError:
                        ok = False
                        break
                    if vals.setdefault(p, v) != v:
                        ok = False  # the same parameter twice in one event, with two values
                        break
                if not ok:
                    continue
            # extend the partial instances waiting for this event with these bindings
            for sig, sub in index.items():
                bucket = sub.get(tuple([vals[p] for p in sig]) if sig else ())
                if not bucket:
                    continue
                fresh = len(sig) != len(vals)
                for inst in bucket.values():
                    origin = inst[9]
                    rt = time - origin
                    ilo = inst[4]
                    if not (ilo[i] <= rt <= inst[5][i]):
                        continue
                    mask = inst[1] | bit
                    if mask == direct:
                        # the last missing event, and no 'after' window to wait for: report
                        # it now (as _recognition, inlined), without building an instance
                        times = ilo[:]
                        times[i] = rt
                        binds = inst[3]
                        if fresh:
                            binds = binds[:]
                            for p, v in vals.items():
                                binds[p] = v
                        self.recognized += 1
                        out.append(
                            _new_tuple(
                                Recognition,
                                (
                                    self._cname,
                                    dict(zip(self._pnames, binds, strict=True)),
                                    dict(zip(self._names, map(origin.__add__, times), strict=True)),
                                ),
                            )
                        )
                        continue
                    # assigned events keep their windows: ``time`` lies in this event's
                    # window, so the minimal network already implies ``t_k <= time + di[k]``
                    # for each of them; only the missing ones narrow
                    hi = inst[5][:]
                    hi[i] = rt
                    lo = ilo[:]
                    lo[i] = rt
                    deadline = _INF
                    todo = missing.get(mask)
                    if todo is None:
                        todo = self._unassigned(mask, i)
                    for j, dji, dij in todo:
                        x = rt - dji
                        if x > lo[j]:
                            lo[j] = x
                        h = rt + dij
                        if h < hi[j]:
                            hi[j] = h
                        else:
                            h = hi[j]
                        if lo[j] > h:
                            deadline = _NEG_INF
                            break
                        if h < deadline:
                            deadline = h
                    if deadline < rt:
                        continue
                    binds = inst[3]
                    if fresh:
                        binds = binds[:]
                        for p, v in vals.items():
                            binds[p] = v
                    # an assigned event's window is its time: ``lo`` doubles as the times
                    created.append(
                        [0, mask, lo, binds, lo, hi, origin + deadline, [], True, origin]
                    )
            # and start a new one, unless another event must come strictly before this one
            if startable:
                binds = self._no_binds
                if vals:
                    binds = binds[:]
                    for p, v in vals.items():
                        binds[p] = v
                created.append([0, bit, negcol, binds, negcol, di, time + mind, [], True, time])
        if not created:
            return out
        full = self._full
        alive = self._alive
        plans = self._plans
        expiry = self._expiry
        fidx = self._fidx
        cap = self._cap
        for inst in created:
            mask = inst[1]
            if mask == full:
                if self._after:
                    self._complete(inst, out)
                else:
                    out.append(self._recognition(inst))
                continue
            # index it under every event it still waits for (as _add, inlined)
            self._seq = seq = self._seq + 1
            inst[0] = seq
            alive[seq] = inst
            binds = inst[3]
            regs = inst[7]
            where = plans.get(mask)
            if where is None:
                where = self._plan(mask)
            for sig, table in where:
                key = tuple([binds[p] for p in sig]) if sig else ()
                bucket = table.get(key)
                if bucket is None:
                    bucket = table[key] = {}
                bucket[seq] = inst
                regs.append((table, key))
            if fidx:
                self._register_forbidden(inst)
            if inst[6] < _INF:
                heapq.heappush(expiry, (inst[6], seq, inst))
            if len(alive) > cap:
                self._evict()
                # eviction may rebuild the heap: later instances go to the new one
                expiry = self._expiry
        return out

    def partial_instances(self) -> int:
        """How many partial instances (and held completions) are alive."""
        return len(self._alive)

    # -- internals ---------------------------------------------------------------------
    def _unassigned(self, mask: int, i: int = 0) -> list[tuple[int, int, int]]:
        """The events ``mask`` leaves unassigned, with ``dist[j][i]``, ``dist[i][j]`` (cached)."""
        got = self._missing.get((mask, i))
        if got is None:
            dist = self.chronicle.dist
            got = self._missing[(mask, i)] = [
                (j, dist[j][i], dist[i][j]) for j in range(len(dist)) if not mask >> j & 1
            ]
            for plan in self._kinds.values():
                for node in plan[1]:
                    if node[0] == i:
                        node[-1][mask] = got
        return got

    def _plan(self, mask: int) -> list[tuple[tuple[int, ...], dict[Any, Any]]]:
        """Where a partial instance with ``mask`` assigned is indexed: (signature, table)."""
        got = self._plans.get(mask)
        if got is None:
            got = []
            dist = self.chronicle.dist
            todo = [i for i, _, _ in self._unassigned(mask)]
            for i in todo:
                if any(dist[i][k] < 0 for k in todo):
                    # another missing event must come strictly before this one, so it
                    # arrives first: waiting for this one now is wasted work
                    continue
                sig = self._sig(mask, i)
                table = self._index[i].get(sig)
                if table is None:
                    table = self._index[i][sig] = {}
                got.append((sig, table))
            self._plans[mask] = got
        return got

    def _sig(self, mask: int, i: int) -> tuple[int, ...]:
        c = self.chronicle
        bound: set[int] = set()
        for nd in c.nodes:
            if mask >> nd.pos & 1:
                bound.update(p for _, p in nd.params)
        return tuple(sorted({p for _, p in c.nodes[i].params if p in bound}))

    def _add(self, inst: _Partial) -> None:
        """Index a new partial instance under every event it still waits for."""
        self._seq += 1
        seq = inst[0] = self._seq
        alive = self._alive
        alive[seq] = inst
        binds = inst[3]
        regs = inst[7]
        for sig, table in self._plan(inst[1]):
            key = tuple([binds[p] for p in sig]) if sig else ()
            bucket = table.get(key)
            if bucket is None:
                bucket = table[key] = {}
            bucket[seq] = inst
            regs.append((table, key))
        if self._fidx:
            self._register_forbidden(inst)
        if inst[6] < _INF:
            heapq.heappush(self._expiry, (inst[6], seq, inst))
        if len(alive) > self._cap:
            self._evict()

    def _evict(self) -> None:
        """Drop the oldest partial instances past the cap (counted), and tidy the heaps."""
        alive = self._alive
        while len(alive) > self._cap:
            _, oldest = alive.popitem(last=False)
            self._drop(oldest)
            self.dropped += 1
        self._compact()

    def _register_forbidden(self, inst: _Partial) -> None:
        mask = inst[1]
        for f in self.chronicle.forbids:
            if not (mask >> f.start & 1):
                continue
            if f.end >= 0:
                if mask >> f.end & 1:
                    continue
            elif inst[9] + inst[2][f.start] + f.hi <= self.clock:
                continue
            parent = self._fidx[f.pos]
            key = tuple([inst[3][p] for _, p in f.params])
            bucket = parent.get(key)
            if bucket is None:
                bucket = parent[key] = {}
            bucket[inst[0]] = inst
            inst[7].append((parent, key))

    def _drop(self, inst: _Partial) -> None:
        """Forget ``inst`` everywhere it is indexed (the heaps clean up lazily)."""
        inst[8] = False
        seq = inst[0]
        for parent, key in inst[7]:
            bucket = parent.get(key)
            if bucket is not None:
                bucket.pop(seq, None)
                if not bucket:
                    del parent[key]
        inst[7] = []

    def _remove(self, inst: _Partial) -> None:
        if self._alive.pop(inst[0], None) is not None:
            self._drop(inst)

    def _compact(self) -> None:
        # dropped and killed instances stay in the heaps until their deadline: rebuild
        # when they outnumber the live ones, so memory follows the cap
        limit = 2 * len(self._alive) + 64
        if len(self._expiry) > limit:
            self._expiry = [e for e in self._expiry if e[2][8] and e[2][6] == e[0]]
            heapq.heapify(self._expiry)
        if len(self._pending) > limit:
            self._pending = [e for e in self._pending if e[2][8]]
            heapq.heapify(self._pending)

    def _expire(self, now: int) -> None:
        heap = self._expiry
        alive = self._alive
        pop = heapq.heappop
        n = 0
        while heap and heap[0][0] < now:
            deadline, seq, inst = pop(heap)
            if inst[8] and inst[6] == deadline:
                del alive[seq]
                inst[8] = False
                for parent, key in inst[7]:
                    bucket = parent[key]
                    del bucket[seq]
                    if not bucket:
                        del parent[key]
                inst[7] = []
                n += 1
        self.expired += n

    def _forbidden(
        self, forbids: list[_Forbid], time: int, args: Mapping[str, Any], old: Any, new: Any
    ) -> None:
        """Apply a forbidden event: kill instances whose window holds it, bound the rest."""
        dist = self.chronicle.dist
        for f in forbids:
            if (f.has_from and old != f.from_) or (f.has_to and new != f.to):
                continue
            try:
                key = tuple([args[a] for a, _ in f.params])
            except KeyError:
                continue
            bucket = self._fidx[f.pos].get(key)
            if not bucket:
                continue
            for inst in list(bucket.values()):
                origin = inst[9]
                ta = origin + inst[2][f.start]
                if f.end < 0:
                    if ta + f.lo < time < ta + f.hi:
                        self._remove(inst)
                        self.killed += 1
                    continue
                if time <= ta:
                    continue
                # the end event must now come no later than this one: bound it and
                # narrow what depends on it
                b = f.end
                rt = time - origin
                if rt >= inst[5][b]:
                    continue
                lo = inst[4]
                hi = inst[5] = inst[5][:]  # it may be the compiled start windows, shared
                db = dist[b]
                mask = inst[1]
                deadline = _INF
                dead = False
                past = self.clock - origin
                for j in range(len(hi)):
                    if mask >> j & 1:
                        continue
                    h = rt + db[j] if j != b else rt
                    if h < hi[j]:
                        hi[j] = h
                    if lo[j] > hi[j] or hi[j] < past:
                        dead = True
                        break
                    if hi[j] < deadline:
                        deadline = hi[j]
                if dead:
                    self._remove(inst)
                    self.killed += 1
                elif origin + deadline < inst[6]:
                    inst[6] = deadline = origin + deadline
                    heapq.heappush(self._expiry, (deadline, inst[0], inst))
        if len(self._expiry) > 2 * len(self._alive) + 64:
            self._compact()  # killed instances and moved deadlines leave stale entries

    def _complete(self, inst: _Partial, out: list[Recognition]) -> None:
        release = _NEG_INF
        for f in self.chronicle.forbids:
            if f.end < 0:
                end = inst[9] + inst[2][f.start] + f.hi
                if end > release:
                    release = end
        if release > self.clock:
            # an 'after' window is still open: hold the recognition until it closes
            self._seq += 1
            inst[0] = self._seq
            self._alive[inst[0]] = inst
            self._register_forbidden(inst)
            heapq.heappush(self._pending, (release, inst[0], inst))
            if len(self._alive) > self._cap:
                self._evict()
            return
        out.append(self._recognition(inst))

    def _release(self, now: int, out: list[Recognition]) -> None:
        heap = self._pending
        while heap and heap[0][0] <= now:
            _, _, inst = heapq.heappop(heap)
            if inst[8]:
                self._remove(inst)
                out.append(self._recognition(inst))

    def _recognition(self, inst: _Partial) -> Recognition:
        self.recognized += 1
        c = self.chronicle
        # tuple.__new__ builds the same NamedTuple without its generated __new__'s frame
        return _new_tuple(
            Recognition,
            (
                c.name,
                dict(zip(c.params, inst[3], strict=True)),
                dict(zip(self._names, map(inst[9].__add__, inst[2]), strict=True)),
            ),
        )


# -- as a knowledge process -----------------------------------------------------------------


def _decode(value: Any, prev: Any) -> tuple[Mapping[str, Any], Any, Any]:
    """An input sample's value as (arguments, old, new)."""
    if isinstance(value, ChangeEvent):
        return {}, value.old, value.new
    if isinstance(value, Recognition):
        return value.bindings, None, value
    if isinstance(value, Mapping):
        return value, value.get("old"), value.get("new")
    return {}, prev, value


class ChronicleProcess(Process):
    """Recognizes one chronicle over input event streams and publishes each recognition."""

    kind = "chronicle"

    def __init__(
        self,
        name: str,
        instance: DyKnowInstance,
        recognizer: ChronicleRecognizer,
        output: StreamGenerator,
    ) -> None:
        super().__init__(name, instance)
        self.recognizer = recognizer
        self.output = output
        self.label = output.label
        self.subscriptions: list[Subscription] = []
        self._last_ta = -(2**63)

    def _callback(self, kind: str, label_args: Mapping[str, Any]) -> Any:
        feed = self.recognizer.feed
        prev: list[Any] = [None]

        def on_samples(batch: list[RawSample]) -> None:
            if not self.running:
                return
            found: list[RawSample] = []
            try:
                for value, tv, ta in batch:
                    args, old, new = _decode(value, prev[0])
                    prev[0] = value
                    if label_args:
                        args = {**args, **label_args}
                    for rec in feed(kind, tv, args, old, new):
                        found.append(self._sample(rec, ta))
            except Exception as exc:
                self._fail(exc)
            if found:
                try:
                    self.output.publish_batch(found)
                except Exception as exc:
                    self._fail(exc)

        return on_samples

    def _sample(self, rec: Recognition, ta: int) -> RawSample:
        if ta <= self._last_ta:
            ta = self._last_ta + 1  # available times are unique per stream
        self._last_ta = ta
        return (rec, max(rec.times.values()), ta)

    def flush(self, now: int | None = None) -> int:
        """Advance the recognizer's clock (default: the instance's) and publish what it releases."""
        t = self.instance.clock.now() if now is None else now
        recs = self.recognizer.advance(t)
        if recs:
            self.output.publish_batch([self._sample(r, t) for r in recs])
        return len(recs)

    def _stop(self) -> None:
        super()._stop()
        for sub in self.subscriptions:
            sub.close()

    def describe(self) -> dict[str, Any]:
        """Adds the inputs, output and the recognizer's counters to the description."""
        d = super().describe()
        d["inputs"] = [s.label for s in self.subscriptions]
        d["output"] = self.label
        d.update(self.recognizer.stats()._asdict())
        return d


def _expand(instance: DyKnowInstance, label: str) -> list[tuple[str, dict[str, str]]]:
    """A label, or the published labels matching its ``{param}`` placeholders, with their values."""
    if "{" not in label:
        return [(label, {})]
    names: list[str] = []
    pattern = ""
    for part in re.split(r"(\{[A-Za-z_][A-Za-z0-9_]*\})", label):
        if part.startswith("{") and part.endswith("}"):
            names.append(part[1:-1])
            pattern += r"([^/]+)"
        else:
            pattern += re.escape(part)
    rx = re.compile(pattern + r"\Z")
    out = []
    for lab in instance.labels():
        m = rx.match(lab)
        if m:
            out.append((lab, dict(zip(names, m.groups(), strict=True))))
    return out


def add_chronicle(
    instance: DyKnowInstance,
    definition: ChronicleSpec | CompiledChronicle | Mapping[str, Any],
    inputs: Mapping[str, str],
    *,
    output: str | None = None,
    name: str | None = None,
) -> ChronicleProcess:
    """Recognize ``definition`` over ``inputs`` (event name → label) and publish recognitions.

    Recognitions (``Recognition`` values) go to ``output``, default ``chronicles/<name>``.
    A label may hold ``{param}`` placeholders (``events/changed/car/{car}/incross``): every
    label published now that matches is read, its placeholders giving the event's
    arguments. Other arguments come from the sample: a ``Recognition``'s bindings (for
    chronicles over chronicles) or a mapping value's keys.
    """
    compiled = (
        definition if isinstance(definition, CompiledChronicle) else compile_chronicle(definition)
    )
    missing = sorted(compiled.kinds - set(inputs))
    if missing:
        raise ChronicleError("inputs", f"no label for event(s) {', '.join(missing)}")
    output = output or f"chronicles/{compiled.name}"
    name = name or f"chronicle:{compiled.name}"
    if name in instance.processes:
        raise ProcessError(f"a process named {name!r} exists already")
    expanded = {kind: _expand(instance, label) for kind, label in inputs.items()}
    for kind, labels in expanded.items():
        if not labels:
            raise ChronicleError(f"inputs.{kind}", f"no published label matches {inputs[kind]!r}")
    gen = instance.create_stream(output, value_type=Recognition)
    proc = ChronicleProcess(name, instance, ChronicleRecognizer(compiled), gen)
    policy = Policy(order=Order.MONOTONE)
    try:
        for kind, labels in expanded.items():
            for label, label_args in labels:
                proc.subscriptions.append(
                    instance.subscribe(label, policy, callback=proc._callback(kind, label_args))
                )
    except Exception:
        proc._stop()
        instance.remove_stream(output)
        raise
    instance.add_process(proc)
    return proc


def recognize_all(
    chronicle: CompiledChronicle | ChronicleSpec | Mapping[str, Any],
    events: Iterable[tuple[str, int, Mapping[str, Any] | None, Any, Any]],
) -> list[Recognition]:
    """Feed ``(kind, time, args, old, new)`` events in order and return every recognition."""
    rec = ChronicleRecognizer(chronicle)
    out: list[Recognition] = []
    for kind, t, args, old, new in events:
        out.extend(rec.feed(kind, t, args, old, new))
    out.extend(rec.advance(_INF))
    return out
