"""``dyknow monitor`` and ``dyknow kpl check``: the reasoning layer offline, on files.

``dyknow monitor FORMULA --trace FILE`` runs an MTL formula over a recorded JSON-lines
trace. Each line of the trace is one state, a JSON object with ``t`` (seconds, strictly
increasing) and a value for every feature (and quantified domain) the formula reads;
other keys are ignored and blank lines skipped. The verdicts are printed as JSON lines:

* by default, each verdict as soon as it is certain, as ``{"t": time it became certain,
  "from": start time of the evaluation, "verdict": true|false}``; the monitor then
  restarts at the next state, so every violation of an ``always`` is reported;
* with ``--every-step``, after the whole trace, one line per state ``{"t": t, "verdict":
  true|false|null, "at": time it became certain or null}`` with the formula evaluated
  from ``t`` (``null``: the trace ends before it is certain).

A bad formula, an unreadable file, a line that is not a JSON object, a missing or
non-increasing ``t``, a missing feature or a value of a kind its atoms cannot read (a
string where the formula compares with a number, a number for a bare feature, which
needs true or false) is reported on stderr with its line number (and column for the
formula) and the exit code is 2.

``dyknow kpl check FILE`` checks a KPL file and prints its errors as ``FILE:LINE:COL: msg``:
exit code 0 with ``ok: N declarations`` when the file checks, 2 otherwise. CU callables
are not imported: they are resolved when an instance is set up from the file.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, TextIO

import typer

from ._cli_common import complain as _complain
from ._cli_node import say as _say

# the reasoning layer loads on first use (``dyknow_core``'s lazy names): each command
# imports what it runs, so the other commands do not pay for the MTL and KPL modules
if TYPE_CHECKING:
    from dyknow_core.reasoning import Verdict

__all__ = ["kpl_app", "monitor"]

kpl_app = typer.Typer(help="KPL files: 'dyknow kpl check FILE'.", no_args_is_help=True)


class _BadInput(Exception):
    pass


def _json_num(x: float) -> float | int:
    return int(x) if x == int(x) and abs(x) < 2**53 else x


# the kinds of JSON value an atom can read (JSON null is always allowed: no value)
_KINDS = {bool: "true or false", float: "a number", str: "a string"}


def _kind(value: Any) -> str:
    """What a JSON value is, in the words of the expected kinds."""
    if isinstance(value, bool):
        return _KINDS[bool]
    if isinstance(value, int | float):
        return _KINDS[float]
    if isinstance(value, str):
        return _KINDS[str]
    if isinstance(value, dict):
        return "an object"
    return "an array" if isinstance(value, list) else type(value).__name__


def _expected(formula: Any) -> dict[str, tuple[bool, set[str] | None]]:
    """Each state key the formula reads → (parameterized, the kinds of value that it can read).

    A bare feature reads true or false; a feature compared to a constant, that constant's
    kind; one ordered against another feature, a number or a string; a domain, an array
    (or object) of members.
    None: any value (a feature tested for equality with another).
    """
    from dyknow_core.reasoning.mtl import (
        Always,
        And,
        Compare,
        Eventually,
        Feature,
        Implies,
        Not,
        Or,
        Quantifier,
        Until,
    )

    out: dict[str, tuple[bool, set[str] | None]] = {}

    def need(feat: Feature, kinds: set[str] | None) -> None:
        params, seen = out.setdefault(feat.name, (bool(feat.args), set()))
        if seen is not None:  # None: one of its atoms reads any value
            out[feat.name] = (params, None if kinds is None else seen | kinds)

    todo = [formula]
    while todo:
        f = todo.pop()
        if isinstance(f, Feature):
            need(f, {_KINDS[bool]})
        elif isinstance(f, Compare):
            for side, other in ((f.left, f.right), (f.right, f.left)):
                if not isinstance(side, Feature):
                    continue
                if not isinstance(other, Feature):
                    need(side, {_kind(other)})
                elif f.op in ("==", "!="):
                    need(side, None)
                else:
                    need(side, {_KINDS[float], _KINDS[str]})
        elif isinstance(f, Not | Always | Eventually):
            todo.append(f.operand)
        elif isinstance(f, And | Or | Implies | Until):
            todo += [f.left, f.right]
        elif isinstance(f, Quantifier):
            out.setdefault(f.domain, (False, {"an array", "an object"}))
            todo.append(f.body)
    return out


def _check_types(
    n: int, obj: dict[str, Any], expected: dict[str, tuple[bool, set[str] | None]]
) -> None:
    """Refuse a state value of a kind its atoms cannot read (they would be false silently)."""
    for key, (params, kinds) in expected.items():
        value = obj[key]
        if value is None:
            continue
        want = "any value" if kinds is None else " or ".join(sorted(kinds))
        if params:
            if not isinstance(value, dict):
                why = f"{key!r} is {_kind(value)}, expected an object of member → {want}"
                raise _BadInput(f"line {n}: {why}")
            members: Any = value.items()
        else:
            members = [(None, value)]
        if kinds is None:
            continue
        for member, v in members:
            got = _kind(v)
            if v is None or got in kinds:
                continue
            where = repr(key) if member is None else f"{key!r}[{member!r}]"
            raise _BadInput(f"line {n}: {where} is {got} ({v!r:.40}), expected {want}")


def _states(
    f: TextIO, keys: list[str], expected: dict[str, tuple[bool, set[str] | None]]
) -> Iterator[tuple[float, dict[str, Any]]]:
    last = -math.inf
    for n, line in enumerate(f, start=1):
        if not line.strip():
            continue
        try:
            obj = json.loads(line)
        except ValueError as exc:
            raise _BadInput(f"line {n}: not JSON: {exc}") from None
        if not isinstance(obj, dict):
            raise _BadInput(f"line {n}: expected a JSON object, got {type(obj).__name__}")
        t = obj.get("t")
        if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
            raise _BadInput(f"line {n}: 't' must be a finite number of seconds, got {t!r}")
        if t <= last:
            raise _BadInput(f"line {n}: t={t} is not after the previous state's t={last}")
        last = t
        missing = [k for k in keys if k not in obj]
        if missing:
            raise _BadInput(f"line {n}: unknown feature(s) {', '.join(map(repr, missing))}")
        _check_types(n, obj, expected)
        yield float(t), obj


def monitor(
    formula: Annotated[
        str,
        typer.Argument(
            metavar="FORMULA",
            help="the formula, e.g. 'always[0,10](speed < 30 -> on_road)'",
        ),
    ],
    trace: Annotated[Path, typer.Option("--trace", help="JSON-lines file, one state per line")],
    every_step: Annotated[
        bool,
        typer.Option(
            "--every-step",
            help="print, for every state t, the verdict of the formula evaluated from t",
        ),
    ] = False,
) -> None:
    """Run an MTL formula over a recorded JSON-lines trace; the verdicts as JSON lines."""
    from dyknow_core.reasoning import (
        Monitor,
        MTLSyntaxError,
        StepMonitor,
        parse_formula,
        state_keys,
    )

    try:
        parsed = parse_formula(formula)
    except MTLSyntaxError as exc:
        _complain(f"dyknow monitor: formula: {exc}")
        raise typer.Exit(2) from None
    keys = state_keys(parsed)
    try:
        f = open(trace, encoding="utf-8")  # noqa: SIM115 - closed below
    except OSError as exc:
        _complain(f"dyknow monitor: cannot read {trace}: {exc.strerror}")
        raise typer.Exit(2) from None
    every: StepMonitor | None = StepMonitor(parsed) if every_step else None
    mon = Monitor(parsed)
    starts: list[float] = []
    decided: dict[float, Verdict] = {}
    code = 0
    try:
        with f:
            for t, state in _states(f, keys, _expected(parsed)):
                if every is not None:
                    starts.append(t)
                    for v in every.step(t, state):
                        decided[v.start] = v
                    continue
                v1 = mon.step(t, state)
                if v1 is not None:
                    line = {"t": _json_num(v1.time), "from": _json_num(v1.start)}
                    line["verdict"] = v1.verdict
                    _say(json.dumps(line))
    except _BadInput as exc:
        _complain(f"dyknow monitor: {trace}: {exc}")
        code = 2
    except UnicodeDecodeError as exc:
        _complain(f"dyknow monitor: {trace}: not UTF-8 text: {exc.reason}")
        code = 2
    for s in starts:
        d = decided.get(s)
        rec = {
            "t": _json_num(s),
            "verdict": None if d is None else d.verdict,
            "at": None if d is None else _json_num(d.time),
        }
        _say(json.dumps(rec))
    raise typer.Exit(code)


@kpl_app.command("check")
def kpl_check_file(
    file: Annotated[Path, typer.Argument(metavar="FILE", help="the KPL file")],
    recording: Annotated[
        Path | None,
        typer.Option(
            "--recording",
            help="a recording 'dyknow replay --kpl FILE' would feed: its labels exist",
        ),
    ] = None,
    node_config: Annotated[
        Path | None,
        typer.Option(
            "--config",
            "-c",
            help="with --recording: a node's config, whose mapping names the recorded "
            "labels as replay --config does",
        ),
    ] = None,
) -> None:
    """Check a KPL file; errors as FILE:LINE:COL: message (exit code 2), else 'ok: N'.

    With --recording, the labels 'dyknow replay --kpl FILE' feeds from that recording (as
    sources the file does not declare) may be used without a declaration.
    """
    from dyknow_core.kpl import KPLCheckError
    from dyknow_core.kpl import check as kpl_check
    from dyknow_core.kpl import parse as kpl_parse

    if node_config is not None and recording is None:
        _complain("dyknow kpl check: --config names a recording's labels: give --recording")
        raise typer.Exit(2)
    try:
        text = file.read_text(encoding="utf-8")
    except OSError as exc:
        _complain(f"{file}: cannot read: {exc.strerror}")
        raise typer.Exit(2) from None
    except UnicodeDecodeError as exc:
        _complain(f"{file}: not UTF-8 text: {exc.reason}")
        raise typer.Exit(2) from None
    known: list[str] = []
    if recording is not None:
        from ._record_cli import ReplayUsageError, load_mapping, recorded_labels, replayed_labels

        # the recording (and config) first: one that is no recording is said whatever
        # the file's syntax, not hidden behind its errors
        try:
            mapping = load_mapping(node_config)[0] if node_config is not None else None
            recorded = recorded_labels(recording, mapping)
        except ReplayUsageError as exc:
            _complain(str(exc))
            raise typer.Exit(2) from None
        try:
            known = replayed_labels(recorded, kpl_parse(text))
        except KPLCheckError:
            pass  # its syntax errors are said below; no label is resolved then
    errors = kpl_check(text, known)
    if errors:
        for e in errors:
            _complain(e.format(str(file)))
        raise typer.Exit(2)
    n = len(kpl_parse(text).decls)
    _say(f"ok: {n} declaration{'' if n == 1 else 's'}")
