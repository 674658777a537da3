"""Online, incremental recognition of a compiled chronicle over a stream of events."""

from __future__ import annotations

import heapq
from collections import OrderedDict
from collections.abc import Mapping
from typing import Any, NamedTuple

from ..._record import register_record_type
from ._compile import CompiledChronicle, _Forbid, compile_chronicle
from ._spec import ChronicleSpec
from ._stn import _INF, _NEG_INF

# -- recognition ----------------------------------------------------------------------------


class Recognition(NamedTuple):
    """One recognized chronicle: its name, parameter bindings, and each event's time (ns)."""

    chronicle: str
    bindings: dict[str, Any]
    times: dict[str, int]


register_record_type(Recognition)  # a replay gives recognitions back as themselves


# A partial instance is a list, not an object: it is made and dropped once per matching
# event, and list literals and indexing are the cheapest Python has. Its slots, by the
# index constants below: ``times`` is the window-lows list itself (an assigned event's
# window is its time), never copied separately. Times and windows are relative to
# ``origin`` (the first assigned event's time), so a new instance shares the compiled
# start windows instead of building two lists per event: they are copied before any
# change. The deadline is absolute (the expiry heap orders by it).
_Partial = list
_SEQ = 0  # its number: the key in the alive table and the index buckets
_MASK = 1  # bit i set when chronicle event i is assigned
_TIMES = 2  # per event, relative to origin: the assigned ones' times (the _LO list)
_BINDS = 3  # per chronicle parameter, its value or _UNBOUND
_LO = 4  # per event, the lower end of its window (relative)
_HI = 5  # per event, the upper end of its window (relative)
_DEADLINE = 6  # absolute: after it a missing event can no longer come in time
_REGS = 7  # (table, key) of every index bucket holding it; None once removed
_ALIVE = 8  # False once expired, killed, completed or dropped
_ORIGIN = 9  # the first assigned event's time (ns)


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
            if heap and heap[0][0] < time:  # checked here: most events let none pass
                self._expire(time)
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
                    origin = inst[_ORIGIN]
                    rt = time - origin
                    ilo = inst[_LO]
                    if not (ilo[i] <= rt <= inst[_HI][i]):
                        continue
                    mask = inst[_MASK] | bit
                    if mask == direct:
                        # the last missing event, and no 'after' window to wait for: report
                        # it now (as _recognition, inlined), without building an instance
                        times = ilo[:]
                        times[i] = rt
                        binds = inst[_BINDS]
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
                    hi = inst[_HI][:]
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
                    binds = inst[_BINDS]
                    if fresh:
                        binds = binds[:]
                        for p, v in vals.items():
                            binds[p] = v
                    # slots in the order of _SEQ.._ORIGIN; an assigned event's window is its
                    # time: ``lo`` doubles as the times
                    created.append(
                        [0, mask, lo, binds, lo, hi, origin + deadline, [], True, origin]
                    )
            # and start a new one (slots as above), unless another event must come strictly
            # before this one
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
            mask = inst[_MASK]
            if mask == full:
                if self._after:
                    self._complete(inst, out)
                else:
                    out.append(self._recognition(inst))
                continue
            # index it under every event it still waits for (as _add, inlined)
            self._seq = seq = self._seq + 1
            inst[_SEQ] = seq
            alive[seq] = inst
            binds = inst[_BINDS]
            regs = inst[_REGS]
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
            if inst[_DEADLINE] < _INF:
                heapq.heappush(expiry, (inst[_DEADLINE], seq, inst))
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
        seq = inst[_SEQ] = self._seq
        alive = self._alive
        alive[seq] = inst
        binds = inst[_BINDS]
        regs = inst[_REGS]
        for sig, table in self._plan(inst[_MASK]):
            key = tuple([binds[p] for p in sig]) if sig else ()
            bucket = table.get(key)
            if bucket is None:
                bucket = table[key] = {}
            bucket[seq] = inst
            regs.append((table, key))
        if self._fidx:
            self._register_forbidden(inst)
        if inst[_DEADLINE] < _INF:
            heapq.heappush(self._expiry, (inst[_DEADLINE], seq, inst))
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
        mask = inst[_MASK]
        for f in self.chronicle.forbids:
            if not (mask >> f.start & 1):
                continue
            if f.end >= 0:
                if mask >> f.end & 1:
                    continue
            elif inst[_ORIGIN] + inst[_TIMES][f.start] + f.hi <= self.clock:
                continue
            parent = self._fidx[f.pos]
            key = tuple([inst[_BINDS][p] for _, p in f.params])
            bucket = parent.get(key)
            if bucket is None:
                bucket = parent[key] = {}
            bucket[inst[_SEQ]] = inst
            inst[_REGS].append((parent, key))

    def _drop(self, inst: _Partial) -> None:
        """Forget ``inst`` everywhere it is indexed (the heaps clean up lazily)."""
        inst[_ALIVE] = False
        seq = inst[_SEQ]
        for parent, key in inst[_REGS]:
            bucket = parent.get(key)
            if bucket is not None:
                bucket.pop(seq, None)
                if not bucket:
                    del parent[key]
        inst[_REGS] = []

    def _remove(self, inst: _Partial) -> None:
        if self._alive.pop(inst[_SEQ], None) is not None:
            self._drop(inst)

    def _compact(self) -> None:
        # dropped and killed instances stay in the heaps until their deadline: rebuild
        # when they outnumber the live ones, so memory follows the cap
        limit = 2 * len(self._alive) + 64
        if len(self._expiry) > limit:
            self._expiry = [e for e in self._expiry if e[2][_ALIVE] and e[2][_DEADLINE] == e[0]]
            heapq.heapify(self._expiry)
        if len(self._pending) > limit:
            self._pending = [e for e in self._pending if e[2][_ALIVE]]
            heapq.heapify(self._pending)

    def _expire(self, now: int) -> None:
        """Forget every instance whose deadline passed before ``now`` (counted expired)."""
        heap = self._expiry
        alive = self._alive
        pop = heapq.heappop
        n = 0
        while heap and heap[0][0] < now:
            deadline, seq, inst = pop(heap)
            if inst[_ALIVE] and inst[_DEADLINE] == deadline:
                del alive[seq]
                inst[_ALIVE] = False
                for parent, key in inst[_REGS]:
                    bucket = parent[key]
                    del bucket[seq]
                    # an unkeyed table has one bucket: kept, as it soon refills
                    if not bucket and key:
                        del parent[key]
                inst[_REGS] = []
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
                origin = inst[_ORIGIN]
                ta = origin + inst[_TIMES][f.start]
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
                if rt >= inst[_HI][b]:
                    continue
                lo = inst[_LO]
                hi = inst[_HI] = inst[_HI][:]  # it may be the compiled start windows, shared
                db = dist[b]
                mask = inst[_MASK]
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
                elif origin + deadline < inst[_DEADLINE]:
                    inst[_DEADLINE] = deadline = origin + deadline
                    heapq.heappush(self._expiry, (deadline, inst[_SEQ], inst))
        if len(self._expiry) > 2 * len(self._alive) + 64:
            self._compact()  # killed instances and moved deadlines leave stale entries

    def _complete(self, inst: _Partial, out: list[Recognition]) -> None:
        release = _NEG_INF
        for f in self.chronicle.forbids:
            if f.end < 0:
                end = inst[_ORIGIN] + inst[_TIMES][f.start] + f.hi
                if end > release:
                    release = end
        if release > self.clock:
            # an 'after' window is still open: hold the recognition until it closes
            self._seq += 1
            inst[_SEQ] = self._seq
            self._alive[inst[_SEQ]] = inst
            self._register_forbidden(inst)
            heapq.heappush(self._pending, (release, inst[_SEQ], inst))
            if len(self._alive) > self._cap:
                self._evict()
            return
        out.append(self._recognition(inst))

    def _release(self, now: int, out: list[Recognition]) -> None:
        heap = self._pending
        while heap and heap[0][0] <= now:
            _, _, inst = heapq.heappop(heap)
            if inst[_ALIVE]:
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
                dict(zip(c.params, inst[_BINDS], strict=True)),
                dict(zip(self._names, map(inst[_ORIGIN].__add__, inst[_TIMES]), strict=True)),
            ),
        )
