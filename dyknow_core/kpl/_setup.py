"""Setting a checked KPL program up on an instance, in dependency order, and undoing it."""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from .._policy import CacheSpec, Policy
from .._process import Input
from .._state import StatePolicy
from ..reasoning import (
    Anchoring,
    LinkType,
    ObjectClass,
    add_anchoring,
    add_chronicle,
    add_monitor,
)
from ._checker import _check_program, _decl_name, _identity, _order
from ._parser import (
    AnchoringDecl,
    ChangesDecl,
    ChronicleDecl,
    ClassDecl,
    CUDecl,
    Decl,
    FuncRef,
    KPLCheckError,
    KPLSetupError,
    LinkDecl,
    MonitorDecl,
    Program,
    SourceDecl,
    StateDecl,
    StreamDecl,
    _parse,
    _sorted,
)

if TYPE_CHECKING:
    from .._instance import DyKnowInstance

log = logging.getLogger(__name__)

Pos = tuple[int, int]  # (line, column), both 1-based

# -- setup ----------------------------------------------------------------------------------


def resolve_callable(module: str, attr: str) -> Callable[..., Any]:
    """Import ``module`` and fetch ``attr`` (dotted for nested attributes)."""
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    if not callable(obj):
        raise TypeError(f"{module}:{attr} is not callable")
    return obj


@dataclass
class KPLApplication:
    """What ``setup`` created on an instance: process names in creation order, domains, notes."""

    instance: DyKnowInstance
    program: Program
    processes: list[str] = field(default_factory=list)
    unsupported: list[str] = field(default_factory=list)
    domains: list[str] = field(default_factory=list)

    def remove(self) -> None:
        """Remove every process this application created, newest first, then its domains.

        A class domain that a running anchoring created since (``add_anchoring`` from
        Python) still uses is left to it.
        """
        instance = self.instance
        for name in reversed(self.processes):
            if name in instance.processes:
                instance.remove_process(name)
        self.processes.clear()
        objects = instance.objects
        in_use = {
            c
            for p in instance.processes.values()
            if isinstance(p, Anchoring) and p.running
            for c in p.classes
        }
        for domain in reversed(self.domains):  # and with each its ``domain/<class>`` label
            if domain in in_use:
                log.info("kpl: class domain %r left: a running anchoring uses it", domain)
            elif domain in objects.domains():
                objects.remove_domain(domain)
        self.domains.clear()


def setup(instance: DyKnowInstance, source: str | Program) -> KPLApplication:
    """Check a KPL text (or parsed program) against ``instance`` and create its declarations.

    Raises ``KPLCheckError`` with every problem if it does not check (nothing is
    created), or ``KPLSetupError`` naming the declaration that failed at creation (a CU
    callable that does not import, a factory that raises); what was created is removed.
    """
    if isinstance(source, Program):
        prog = source
        errors = _check_program(prog, instance.labels())
    else:
        prog, errors = _parse(source)
        errors += _check_program(prog, instance.labels()) if not errors else []
    if errors:
        raise KPLCheckError(_sorted(errors))
    app = KPLApplication(instance, prog)
    anchoring = [d for d in prog.decls if isinstance(d, ClassDecl | LinkDecl | AnchoringDecl)]
    d: Decl | None = None
    try:
        for d in _order(prog.decls, set(instance.labels())):
            if not isinstance(d, ClassDecl | LinkDecl | AnchoringDecl):
                _create(app, d)
        if anchoring:
            d = anchoring[0]
            _create_anchoring(app, anchoring)
    except Exception as exc:
        app.remove()
        if isinstance(exc, KPLSetupError):
            raise
        pos = d.pos if d is not None else (1, 1)
        what = f"{d.kind} {_decl_name(d)!r}" if d is not None else "setup"
        raise KPLSetupError(pos, f"{what}: {exc}") from exc
    return app


def _resolve(ref: FuncRef, what: str) -> Callable[..., Any]:
    try:
        return resolve_callable(ref.module, ref.attr)
    except Exception as exc:
        raise KPLSetupError(
            ref.pos, f"{what}: {ref.module}:{ref.attr}: {type(exc).__name__}: {exc}"
        ) from exc


def _create_anchoring(
    app: KPLApplication, decls: list[ClassDecl | LinkDecl | AnchoringDecl]
) -> None:
    classes: list[ObjectClass] = []
    links: list[LinkType] = []
    period, output = 1.0, "events/anchoring"
    for d in decls:
        if isinstance(d, ClassDecl):
            rels = {
                k: _resolve(r, f"class {d.name!r} relation {k!r}") for k, r in d.relations.items()
            }
            classes.append(
                ObjectClass(
                    name=d.name,
                    features=d.features.as_dict(),
                    relations=rels,
                    **d.fields.as_dict(),
                )
            )
        elif isinstance(d, LinkDecl):
            compute = _resolve(d.compute, f"link {d.name!r} compute") if d.compute else None
            links.append(LinkType(name=d.name, compute=compute, **d.fields.as_dict()))
        else:
            period, output = d.period, d.output
    before = set(app.instance.objects.domains())
    try:
        proc = add_anchoring(app.instance, classes, links, period=period, output=output)
    finally:  # the class domains it created, even if it then failed
        app.domains += [n for n in app.instance.objects.domains() if n not in before]
    app.processes.append(proc.name)


def _create(app: KPLApplication, d: Decl) -> None:
    inst = app.instance
    if isinstance(d, SourceDecl):
        cache = CacheSpec(**d.cache.as_dict()) if d.cache else None
        app.processes.append(inst.add_source(d.label, cache=cache).name)
    elif isinstance(d, CUDecl):
        try:
            target = resolve_callable(d.module, d.attr)
            fn = target(**d.args.as_dict()) if d.args is not None else target
        except Exception as exc:
            raise KPLSetupError(
                d.pos, f"cu {d.name!r}: {d.module}:{d.attr}: {type(exc).__name__}: {exc}"
            ) from exc
        inputs = [
            Input(i.ref.label, Policy(**i.policy.as_dict()) if i.policy else Policy())
            for i in d.inputs
        ]
        app.processes.append(inst.add_cu(d.name, fn, inputs, d.output.label).name)
    elif isinstance(d, StreamDecl):
        policy = Policy(**d.policy.as_dict()) if d.policy else Policy()
        name = f"stream:{d.label}"
        app.processes.append(
            inst.add_cu(name, _identity, [Input(d.source.label, policy)], d.label).name
        )
    elif isinstance(d, StateDecl):
        comps = {e.key: e.value for e in d.components.entries}
        proc = inst.add_state(d.label, comps, StatePolicy(**d.policy.as_dict()))
        app.processes.append(proc.name)
    elif isinstance(d, ChangesDecl):
        ev = inst.add_change_events(d.source.label, d.change, name=f"changes:{d.source.label}")
        app.processes.append(ev.name)
    elif isinstance(d, MonitorDecl):
        mon = add_monitor(
            inst,
            d.formula,
            label=d.label,
            components=d.components.as_dict() if d.components else None,
            period=d.period,
            max_delay=d.max_delay,
            name=f"monitor:{d.name}",
        )
        app.processes.append(mon.name)
    elif isinstance(d, ChronicleDecl):
        chron = add_chronicle(
            inst,
            d.spec(),
            {k: r.label for k, r in d.inputs.items()},
            output=d.label,
            name=f"chronicle:{d.name}",
        )
        app.processes.append(chron.name)
    else:
        msg = f"line {d.pos[0]}: {d.kind} {d.name!r} is not yet supported at setup (ignored)"
        app.unsupported.append(msg)
        log.warning("KPL: %s", msg)
