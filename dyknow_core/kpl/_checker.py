"""Checking a KPL program: policies, labels, formulas and chronicles, every error at once."""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable
from typing import Any

from .._exceptions import PolicyError
from .._policy import CacheSpec, Change, Policy, check_duration
from .._state import StatePolicy
from ..reasoning import (
    ChronicleError,
    LinkType,
    MTLSyntaxError,
    ObjectClass,
    compile_chronicle,
    parse_formula,
    state_keys,
)
from ._parser import (
    _CLASS_FORMULAS,
    _LINK_FORMULAS,
    AnchoringDecl,
    ChangesDecl,
    ChronicleDecl,
    ClassDecl,
    CUDecl,
    Decl,
    KPLError,
    LinkDecl,
    MappingNode,
    MonitorDecl,
    Program,
    Ref,
    SourceDecl,
    StateDecl,
    StreamDecl,
    UnsupportedDecl,
    _excerpt,
    _Fail,
    _parse,
    _sorted,
)

log = logging.getLogger(__name__)

Pos = tuple[int, int]  # (line, column), both 1-based


def _identity(value: Any) -> Any:
    return value


# -- checking -------------------------------------------------------------------------------


def provides(d: Decl) -> list[str]:
    """The labels a declaration creates (what other declarations may reference)."""
    if isinstance(d, SourceDecl | StreamDecl | StateDecl | ChangesDecl):
        return [d.label]
    if isinstance(d, CUDecl):
        return [d.output.label]
    if isinstance(d, MonitorDecl):
        return [d.label, f"{d.label}/state"]
    if isinstance(d, ChronicleDecl):
        return [d.label]
    if isinstance(d, AnchoringDecl):
        return [d.output]
    return []


def _monitor_refs(d: MonitorDecl) -> list[Ref]:
    comps = d.components.as_dict() if d.components else {}
    where = {e.key: e.value_pos for e in d.components.entries} if d.components else {}
    try:
        keys = state_keys(parse_formula(d.formula))
    except MTLSyntaxError:
        return []
    return [Ref(comps.get(k, k), where.get(k, d.formula_pos)) for k in keys]


def _needs(d: Decl) -> list[Ref]:
    if isinstance(d, CUDecl):
        return [i.ref for i in d.inputs]
    if isinstance(d, StreamDecl | ChangesDecl):
        return [d.source]
    if isinstance(d, StateDecl):
        return [Ref(e.value, e.value_pos) for e in d.components.entries]
    if isinstance(d, MonitorDecl):
        return _monitor_refs(d)
    if isinstance(d, ChronicleDecl):
        return list(d.inputs.values())
    if isinstance(d, ClassDecl):
        return [Ref(e.value, e.value_pos) for e in d.fields.entries if e.key == "create_from"]
    return []


def _pattern(label: str) -> re.Pattern[str] | None:
    # A chronicle input "car/{car}/behind" reads every label matching it.
    if "{" not in label:
        return None
    parts = re.split(r"\{[A-Za-z_][A-Za-z0-9_]*\}", label)
    return re.compile("[^/]+".join(re.escape(p) for p in parts) + r"\Z")


def _decl_name(d: Decl) -> str:
    return (
        d.name
        if isinstance(
            d,
            CUDecl
            | MonitorDecl
            | ChronicleDecl
            | ClassDecl
            | LinkDecl
            | AnchoringDecl
            | UnsupportedDecl,
        )
        else (d.label)
    )


class _Checker:
    def __init__(self, prog: Program, known: Iterable[str], resolve: bool) -> None:
        self.resolve = resolve
        self.prog = prog
        self.known = set(known)
        self.errors: list[tuple[Pos, str]] = []

    def err(self, pos: Pos, msg: str) -> None:
        self.errors.append((pos, msg))

    def policy(self, node: MappingNode | None, model: type[Any], what: str) -> None:
        if node is None:
            return
        fields = model.model_fields
        ok = True
        for e in node.entries:
            if e.key not in fields:
                self.err(
                    e.key_pos,
                    f"unknown {what} field {e.key!r} (known: {', '.join(fields)})",
                )
                ok = False
        if not ok:
            return
        try:
            model(**node.as_dict())
        except PolicyError as exc:
            top = exc.field.split(".")[0]
            self.err(node.where(top), f"{what} field {exc.field!r}: {exc.reason}")

    def run(self) -> None:
        seen: dict[tuple[str, str], Pos] = {}
        providers: dict[str, Pos] = {}
        for d in self.prog.decls:
            # a process name is `N` (cu), `monitor:N`, `chronicle:N`: each kind names its own
            key = (d.kind, _decl_name(d))
            dup = key in seen and not isinstance(d, SourceDecl | StreamDecl | StateDecl)
            if dup:
                self.err(d.pos, f"duplicate {d.kind} {key[1]!r} (first declared at line "
                         f"{seen[key][0]})")  # fmt: skip
            seen.setdefault(key, d.pos)
            for lab in [] if dup else provides(d):
                if lab in providers:
                    self.err(d.pos, f"label {lab!r} is declared twice (first at line "
                             f"{providers[lab][0]})")  # fmt: skip
                elif lab in self.known:
                    self.err(d.pos, f"label {lab!r} exists already on the instance")
                providers.setdefault(lab, d.pos)
            self.decl(d)
        self.anchoring()
        if not self.resolve:
            return
        avail = set(providers) | self.known
        for d in self.prog.decls:
            for ref in _needs(d):
                pat = _pattern(ref.label)
                if pat is not None:
                    if not any(pat.match(lab) for lab in avail):
                        self.err(ref.pos, f"no declared or existing label matches {ref.label!r}")
                elif ref.label not in avail:
                    self.err(ref.pos, f"unknown label {ref.label!r}: no declaration provides it")
        self.cycles()

    def decl(self, d: Decl) -> None:
        if isinstance(d, SourceDecl):
            self.policy(d.cache, CacheSpec, "cache")
        elif isinstance(d, CUDecl):
            for i in d.inputs:
                self.policy(i.policy, Policy, "policy")
        elif isinstance(d, StreamDecl):
            self.policy(d.policy, Policy, "policy")
        elif isinstance(d, StateDecl):
            self.policy(d.policy, StatePolicy, "state policy")
            if not d.components.entries:
                self.err(d.components.pos, "a state needs at least one component")
        elif isinstance(d, ChangesDecl):
            try:
                Change.parse(d.change)
            except PolicyError as exc:
                self.err(d.change_pos, f"change: {exc.reason}")
            except ValueError as exc:  # pragma: no cover - Change.parse wraps pydantic's
                self.err(d.change_pos, f"change: {exc}")
        elif isinstance(d, MonitorDecl):
            self.monitor(d)
        elif isinstance(d, ChronicleDecl):
            self.chronicle(d)
        elif isinstance(d, ClassDecl):
            self.model(d, ObjectClass, _CLASS_FORMULAS)
        elif isinstance(d, LinkDecl):
            self.model(d, LinkType, _LINK_FORMULAS)

    def formula(self, text: str, where: Pos, what: str = "formula") -> set[str] | None:
        try:
            return set(state_keys(parse_formula(text)))
        except MTLSyntaxError as exc:
            # The formula sits in a one-line string: its column 1 is just after the quote.
            line, col = where
            pos = (line, col + exc.column) if exc.line == 1 else (line + exc.line - 1, exc.column)
            self.err(pos, f"{what}: {exc.message}")
            return None

    def model(self, d: ClassDecl | LinkDecl, model: type[Any], formulas: tuple[str, ...]) -> None:
        ok = True
        for e in d.fields.entries:
            if e.key in formulas and self.formula(e.value, e.value_pos, e.key) is None:
                ok = False
        if not ok:
            return
        data: dict[str, Any] = {"name": d.name, **d.fields.as_dict()}
        if isinstance(d, ClassDecl):
            data["features"] = d.features.as_dict()
            data["relations"] = {k: _identity for k in d.relations}
        elif d.compute is not None:
            data["compute"] = _identity
        try:
            model(**data)
        except PolicyError as exc:
            top, _, rest = exc.field.partition(".")
            if top == "features" and rest and isinstance(d, ClassDecl):
                pos = d.features.where(rest)
            elif top in ("relations", "compute"):
                ref = d.relations.get(rest) if isinstance(d, ClassDecl) else d.compute
                pos = ref.pos if ref is not None else d.pos
            else:
                # create_from is written in the create clause; a missing one points there too
                written = {e.key for e in d.fields.entries}
                pos = d.fields.where(
                    top if top in written else {"create_from": "create"}.get(top, top)
                )
            self.err(pos, f"{d.kind} {d.name!r}: {exc.field}: {exc.reason}")

    def anchoring(self) -> None:
        classes: dict[str, ClassDecl] = {}
        for d in self.prog.decls:
            if isinstance(d, ClassDecl):
                base = next((e for e in d.fields.entries if e.key == "base"), None)
                if base is not None and base.value != d.name and base.value not in classes:
                    later = any(
                        isinstance(o, ClassDecl) and o.name == base.value for o in self.prog.decls
                    )
                    why = "must be declared before it" if later else "is not declared"
                    self.err(base.value_pos, f"base class {base.value!r} {why}")
                classes.setdefault(d.name, d)
            elif isinstance(d, LinkDecl):
                for e in d.fields.entries:
                    if e.key in ("from_class", "to_class") and not any(
                        isinstance(o, ClassDecl) and o.name == e.value for o in self.prog.decls
                    ):
                        self.err(e.value_pos, f"unknown class {e.value!r}")
            elif isinstance(d, AnchoringDecl):
                try:
                    check_duration("period", d.period, minimum=1e-6)
                except ValueError as exc:
                    self.err(d.period_pos, f"anchoring period: {exc}")
        if not classes:
            for d in self.prog.decls:
                if isinstance(d, LinkDecl | AnchoringDecl):
                    what = "anchoring" if isinstance(d, AnchoringDecl) else f"link {d.name!r}"
                    self.err(d.pos, f"{what} needs at least one class declaration")
        elif "events/anchoring" in self.known and not any(
            isinstance(d, AnchoringDecl) for d in self.prog.decls
        ):
            self.err(
                next(iter(classes.values())).pos,
                "label 'events/anchoring' exists already on the instance "
                "(give another with 'anchoring every P output LABEL')",
            )

    def monitor(self, d: MonitorDecl) -> None:
        keys = self.formula(d.formula, d.formula_pos)
        if keys is None:
            return
        if not keys:
            self.err(d.formula_pos, "formula reads no feature")
        for e in d.components.entries if d.components else []:
            if e.key not in keys:
                self.err(e.key_pos, f"formula reads no feature {e.key!r}")
        try:
            StatePolicy(period=d.period, max_delay=d.max_delay)
        except PolicyError as exc:
            self.err(d.pos, f"monitor {exc.field}: {exc.reason}")

    def chronicle(self, d: ChronicleDecl) -> None:
        try:
            compiled = compile_chronicle(d.spec())
        except ChronicleError as exc:
            m = re.match(r"(events|constraints|forbidden)\.(\d+)", exc.field)
            pos = d.item_pos.get(m.group(0), d.pos) if m else d.pos
            self.err(pos, f"chronicle {d.name!r}: {exc.field}: {exc.reason}")
            return
        for kind in sorted(compiled.kinds - set(d.inputs)):
            # at the first event (or forbidden pattern) of that kind, where it is written
            uses = [
                d.item_pos.get(f"{group}.{n}", d.pos)
                for group, items in (("events", d.events), ("forbidden", d.forbidden))
                for n, item in enumerate(items)
                if item.get("event") == kind
            ]
            where = min(uses, default=d.pos)
            self.err(where, f"chronicle {d.name!r}: no 'input {kind} = LABEL' for event {kind!r}")

    def cycles(self) -> None:
        try:
            _order(self.prog.decls, self.known)
        except _Fail as exc:
            self.err(exc.pos, exc.message)


def _order(decls: list[Decl], known: set[str]) -> list[Decl]:
    """The declarations in dependency order (providers first); a cycle is a _Fail."""
    by_label: dict[str, int] = {}
    for n, d in enumerate(decls):
        for lab in provides(d):
            by_label.setdefault(lab, n)
    deps: list[set[int]] = []
    for d in decls:
        s: set[int] = set()
        for ref in _needs(d):
            pat = _pattern(ref.label)
            if pat is None:
                if ref.label in by_label and ref.label not in known:
                    s.add(by_label[ref.label])
            else:
                s.update(n for lab, n in by_label.items() if pat.match(lab))
        deps.append(s)
    done: list[int] = []
    state = [0] * len(decls)  # 0 new, 1 in progress, 2 done

    def visit(n: int) -> None:
        if state[n] == 2:
            return
        if state[n] == 1:
            raise _Fail(decls[n].pos, f"{decls[n].kind} {_decl_name(decls[n])!r} depends on itself")
        state[n] = 1
        for m in sorted(deps[n]):
            visit(m)
        state[n] = 2
        done.append(n)

    for n in range(len(decls)):
        visit(n)
    return [decls[n] for n in done]


def check(text: str, known_labels: Iterable[str] = ()) -> list[KPLError]:
    """Every problem in a KPL text (syntax, policies, labels, formulas, chronicles), in order.

    ``known_labels`` are streams that exist already (an instance's labels) and may be
    referenced without being declared. CU callables are not imported here.
    """
    prog, errors = _parse(text)
    # A declaration dropped by a syntax error may provide labels others use: resolving
    # references then would only add noise.
    return _sorted(errors + _check_program(prog, known_labels, resolve=not errors))


def _check_program(
    prog: Program, known_labels: Iterable[str], *, resolve: bool = True
) -> list[KPLError]:
    c = _Checker(prog, known_labels, resolve)
    c.run()
    lines = prog.text.splitlines()
    return [KPLError(p[0], p[1], m, _excerpt(lines, *p)) for p, m in c.errors]
