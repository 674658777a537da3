"""The compiled chronicle: nodes, minimal distance matrix and indexes the hot path reads."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

from pydantic import ValidationError

from ..._time import seconds_to_ns
from ._spec import ChronicleError, ChronicleSpec
from ._stn import _INF, TemporalNetwork

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

    stn = TemporalNetwork(n)
    for k, c in enumerate(spec.constraints):
        a = node(c.start, f"constraints.{k}.start")
        b = node(c.end, f"constraints.{k}.end")
        if a == b:
            raise ChronicleError(f"constraints.{k}", "a constraint needs two different events")
        if c.lo is not None and c.hi is not None and c.lo > c.hi:
            raise ChronicleError(f"constraints.{k}", f"lo {c.lo} is greater than hi {c.hi}")
        stn.constrain(
            a,
            b,
            None if c.lo is None else seconds_to_ns(c.lo),
            None if c.hi is None else seconds_to_ns(c.hi),
            f"{c.start} -> {c.end} [{c.lo}, {c.hi}]",
        )
    dist = stn.minimal()

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
