"""MTL monitors: the restarting monitor, and monitoring in an instance."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

from ..._exceptions import ProcessError
from ..._process import Process
from ..._state import StatePolicy
from ..._time import NS_PER_S
from ._engine import Verdict, _fast_supported, _run_restarting
from ._progression import Node, Residual, _compile
from ._semantics import _field_at
from ._syntax import Compare, Feature, Formula, _as_formula, _walk, state_keys

if TYPE_CHECKING:
    from ..._instance import DyKnowInstance
    from ..._stream import StreamGenerator, Subscription

log = logging.getLogger("dyknow_core.monitor")

# -- monitors ------------------------------------------------------------------------------


class Monitor:
    """Progresses one formula over (t, state) steps and reports each certain verdict.

    After a verdict the monitor restarts at the next state (``restart=True``), so an
    ``always`` monitor reports every violation, each for the formula evaluated from the
    state after the previous verdict.
    """

    __slots__ = ("_fresh", "_node", "_start", "formula", "restart", "text")

    def __init__(self, formula: Formula | str, *, restart: bool = True) -> None:
        self.formula = _as_formula(formula)
        self.text = formula if isinstance(formula, str) else str(formula)
        self.restart = restart
        self._fresh = _compile(self.formula, {})
        self._node: Node | None = None
        self._start = 0.0

    @property
    def residual(self) -> bool | Residual | None:
        """What the current evaluation still requires (None before the first state)."""
        n = self._node
        if n is None or isinstance(n, bool):
            return n
        return Residual(n)

    def step(self, t: float, state: Mapping[str, Any]) -> Verdict | None:
        """Progress through one state; the verdict it made certain, if any."""
        n = self._node
        if n is None:
            n = self._fresh
            self._start = t
        elif n is True or n is False:
            return None  # decided and not restarting
        r = n if n is True or n is False else n.prog(state, t)
        if r is True or r is False:
            self._node = None if self.restart else r
            return Verdict(self._start, t, r)
        self._node = r
        return None

    def run(self, trace: Iterable[tuple[float, Mapping[str, Any]]]) -> list[Verdict]:
        """Every verdict over a whole trace."""
        if self.restart and self._node is None and _fast_supported(self.formula):
            # the every-step engine, reading off the restarting evaluations' verdicts
            # (measured: a third faster on the bench formula), then the evaluation
            # left open is progressed, so that step and residual go on from it
            verdicts, rest = _run_restarting(self.formula, trace)
            for t, s in rest:
                if self.step(t, s) is not None:
                    raise AssertionError("the engines disagree")  # pragma: no cover
            return verdicts
        out = []
        step = self.step
        for t, s in trace:
            v = step(t, s)
            if v is not None:
                out.append(v)
        return out


# -- in an instance ------------------------------------------------------------------------


class MonitorProcess(Process):
    """Monitors a formula over a state stream and publishes its verdicts as a stream."""

    kind = "monitor"

    def __init__(
        self,
        name: str,
        instance: DyKnowInstance,
        formula: Formula,
        text: str,
        state_name: str,
        output: StreamGenerator,
    ) -> None:
        super().__init__(name, instance)
        self.formula = formula
        self.text = text
        self.monitor = Monitor(formula)
        self.state_name = state_name
        self.output = output
        self.label = output.label
        self.subscription: Subscription | None = None
        self.verdicts = 0
        self._last_ta = -(2**63)
        self.warnings: list[str] = []
        # features compared with a number, until their first value was seen: a message
        # (a mapping of fields) there makes the comparison false (true for !=), silently
        self._unchecked = _compared_with_numbers(formula)

    def _on_states(self, batch: list[tuple[Any, int, int]]) -> None:
        if not self.running:
            return
        if self._unchecked:
            self._check_values(batch)
        out: list[tuple[Any, int, int]] = []
        step = self.monitor.step
        for value, tv, ta in batch:
            try:
                v = step(tv / NS_PER_S, value)
            except Exception as exc:
                self._fail(exc)
                continue
            if v is not None:
                if ta <= self._last_ta:
                    ta = self._last_ta + 1  # available times are unique per stream
                self._last_ta = ta
                val = {"verdict": v.verdict, "formula": self.text, "start": round(v.start * 1e9)}
                out.append((val, tv, ta))
        if out:
            self.verdicts += len(out)
            try:
                self.output.publish_batch(out)
            except Exception as exc:
                self._fail(exc)

    def _check_values(self, batch: list[tuple[Any, int, int]]) -> None:
        """Warn, once per feature, when one compared with a number holds a message."""
        unchecked = self._unchecked
        for state, _, _ in batch:
            if not isinstance(state, Mapping):
                continue
            for name in [n for n in unchecked if state.get(n) is not None]:
                atom = unchecked.pop(name)
                value = state[name]
                if isinstance(value, Mapping):
                    warning = _message_warning(self.label, name, atom, value)
                    self.warnings.append(warning)
                    log.warning("%s", warning)
            if not unchecked:
                return

    def _stop(self) -> None:
        super()._stop()
        if self.subscription is not None:
            self.subscription.close()
        if self.state_name in self.instance.processes:
            self.instance.remove_process(self.state_name)

    def describe(self) -> dict[str, Any]:
        """Adds the formula, the state process, the verdict stream and the count."""
        d = super().describe()
        d.update(formula=self.text, state=self.state_name, output=self.label)
        d["verdicts"] = self.verdicts
        if self.warnings:
            d["warnings"] = list(self.warnings)
        return d


def _compared_with_numbers(formula: Formula) -> dict[str, str]:
    """Each feature read whole (no field) and compared with a number: the first such atom."""
    out: dict[str, str] = {}
    for node in _walk(formula):
        if not isinstance(node, Compare):
            continue
        for side, other in ((node.left, node.right), (node.right, node.left)):
            if (
                isinstance(side, Feature)
                and not side.args
                and isinstance(other, int | float)
                and not isinstance(other, bool)
            ):
                out.setdefault(side.name, str(node))
    return out


def _leaves(value: Mapping[str, Any], prefix: str = "", depth: int = 4) -> list[str]:
    """The paths of a message's fields, nested ones dotted (``pose.position.x``)."""
    out: list[str] = []
    for k, v in value.items():
        path = f"{prefix}{k}"
        if isinstance(v, Mapping) and v and depth > 1:
            out += _leaves(v, f"{path}.", depth - 1)
        else:
            out.append(path)
    return out


def _message_warning(label: str, name: str, atom: str, value: Mapping[str, Any]) -> str:
    """What a user is told when feature ``name`` holds a message but is compared with a number."""
    fields = _leaves(value)
    numeric = [f for f in fields if type(_field_at(value, f)) in (int, float)]
    pick = "data" if "data" in fields else (numeric or fields or ["data"])[0]
    shown = ", ".join(fields[:8]) + (", …" if len(fields) > 8 else "")
    return (
        f"monitor {label}: feature {name!r} holds a message with fields ({shown}), not a "
        f"number: {atom} compares a message with a number, false with <, <=, >, >= and == "
        f"and true with !=, whatever the message holds. Compare one of its "
        f'fields: {name}("{pick}")'
    )


def add_monitor(
    instance: DyKnowInstance,
    formula: Formula | str,
    *,
    label: str | None = None,
    state_label: str | None = None,
    components: Mapping[str, str] | None = None,
    period: float = 1.0,
    max_delay: float | None = None,
    name: str | None = None,
) -> MonitorProcess:
    """Monitor ``formula`` on a state of exactly its features; verdicts published on ``label``.

    ``components`` maps each feature (and quantified domain) to the label it is read
    from; a feature not in it is read from the label of its own name. The state is made
    with ``StatePolicy(period, max_delay=max_delay)``; each verdict is a sample with value
    ``{"verdict": bool, "formula": text, "start": ns}`` at the valid time of the state
    that made it certain (a window is closed by the first state after it, so at most a
    period late). A quantified domain is a component too: its stream carries the current
    members (a list), and a parameterized feature's stream a mapping member → value.
    Removing the monitor removes its state process too.
    """
    f = _as_formula(formula)
    text = formula if isinstance(formula, str) else str(formula)
    keys = state_keys(f)
    if not keys:
        raise ProcessError(f"formula {text!r} reads no feature")
    comps = {k: (components or {}).get(k, k) for k in keys}
    if label is None:
        n = 0
        while instance.has_label(f"monitor/{n}") or instance.has_label(f"monitor/{n}/state"):
            n += 1
        label = f"monitor/{n}"
    name = name or f"monitor:{label}"
    if name in instance.processes:
        raise ProcessError(f"a process named {name!r} exists already")
    state_label = state_label or f"{label}/state"
    state = instance.add_state(state_label, comps, StatePolicy(period=period, max_delay=max_delay))
    try:
        out = instance.create_stream(label, value_type=dict)
    except Exception:
        instance.remove_process(state.name)
        raise
    proc = MonitorProcess(name, instance, f, text, state.name, out)
    try:
        proc.subscription = instance.subscribe(state_label, callback=proc._on_states)
        instance.add_process(proc)
    except Exception:
        proc._stop()
        instance.remove_stream(label)
        raise
    return proc
