"""``dyknow monitor FORMULA --trace FILE``: run a formula over a recorded JSON-lines trace.

Each line of the trace is one state, a JSON object with ``t`` (seconds, strictly
increasing) and a value for every feature (and quantified domain) the formula reads;
other keys are ignored and blank lines skipped. The verdicts are printed as JSON lines:

* by default, each verdict as soon as it is certain, as ``{"t": time it became certain,
  "from": start time of the evaluation, "verdict": true|false}``; the monitor then
  restarts at the next state, so every violation of an ``always`` is reported;
* with ``--every-step``, after the whole trace, one line per state ``{"t": t, "verdict":
  true|false|null, "at": time it became certain or null}`` with the formula evaluated
  from ``t`` (``null``: the trace ends before it is certain).

A bad formula, an unreadable file, a line that is not a JSON object, a missing or
non-increasing ``t`` or a missing feature is reported on stderr with its line number
(and column for the formula) and the exit code is 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from typing import Any, TextIO

from .reasoning.mtl import Monitor, MTLSyntaxError, StepMonitor, Verdict, parse, state_keys


class _BadInput(Exception):
    pass


def _json_num(x: float) -> float | int:
    return int(x) if x == int(x) and abs(x) < 2**53 else x


def build_parser(prog: str = "dyknow monitor") -> argparse.ArgumentParser:
    """The argument parser of the ``monitor`` command."""
    p = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    add_arguments(p)
    return p


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Add the ``monitor`` arguments to a (sub)parser."""
    p.add_argument("formula", help="the formula, e.g. 'always[0,10](speed < 30 -> on_road)'")
    p.add_argument("--trace", required=True, help="JSON-lines file, one state per line")
    p.add_argument(
        "--every-step",
        action="store_true",
        help="print, for every state t, the verdict of the formula evaluated from t",
    )


def _states(f: TextIO, keys: list[str]) -> Any:
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
        yield float(t), obj


def run(args: argparse.Namespace, out: TextIO | None = None, err: TextIO | None = None) -> int:
    """Run the command on parsed arguments (printing to ``out``/``err``); the exit code."""
    out = out or sys.stdout
    err = err or sys.stderr
    try:
        formula = parse(args.formula)
    except MTLSyntaxError as exc:
        print(f"dyknow monitor: formula: {exc}", file=err)
        return 2
    keys = state_keys(formula)
    try:
        f = open(args.trace, encoding="utf-8")  # noqa: SIM115 - closed below
    except OSError as exc:
        print(f"dyknow monitor: cannot read {args.trace}: {exc.strerror}", file=err)
        return 2
    every: StepMonitor | None = StepMonitor(formula) if args.every_step else None
    mon = Monitor(formula)
    starts: list[float] = []
    decided: dict[float, Verdict] = {}
    code = 0
    try:
        with f:
            for t, state in _states(f, keys):
                if every is not None:
                    starts.append(t)
                    for v in every.step(t, state):
                        decided[v.start] = v
                    continue
                v1 = mon.step(t, state)
                if v1 is not None:
                    line = {"t": _json_num(v1.time), "from": _json_num(v1.start)}
                    line["verdict"] = v1.verdict
                    print(json.dumps(line), file=out)
    except _BadInput as exc:
        print(f"dyknow monitor: {args.trace}: {exc}", file=err)
        code = 2
    except UnicodeDecodeError as exc:
        print(f"dyknow monitor: {args.trace}: not UTF-8 text: {exc.reason}", file=err)
        code = 2
    for s in starts:
        d = decided.get(s)
        rec = {
            "t": _json_num(s),
            "verdict": None if d is None else d.verdict,
            "at": None if d is None else _json_num(d.time),
        }
        print(json.dumps(rec), file=out)
    return code


def main(argv: Sequence[str] | None = None) -> int:
    """``dyknow monitor`` as a function: parse ``argv`` and run; the exit code."""
    return run(build_parser().parse_args(argv))
