"""MTL progression: ``always[0,10](speed < 30 -> eventually[0,5] on_road)`` over 100 k states.

Same generated trace (non-uniform steps of 0.05-0.95 s, speed a random walk in [0, 40],
on_road in bursts), same process, runs interleaved, best of ``REPEAT``:

- ours: :class:`dyknow_core.reasoning.mtl.Monitor` — one verdict as soon as it is certain,
  then a restart at the next state (the execution-monitoring mode; ``run`` reads these
  verdicts off the every-step evaluation, ``step`` progresses one formula);
- mstlo-python (Rust core, ``EagerQualitative``): ``G[0, 10](speed < 30 -> F[0, 5](on_road >
  0.5))`` fed with ``update_batch`` (prepared outside the timing), one verdict per
  timestamp. Its signals are dense, piecewise constant, which for this formula (windows
  starting at 0) gives the same value at each sample time as our pointwise semantics;
- reelay (C++, dense timed monitor) on the hand-written past-time rewrite
  ``historically[0:10]((once[5:5]{speed < 30}) -> (once[0:5]{on_road}))``: the verdict for
  start t is its value at t + 15 (so never eager: 15 s late by construction).

Each tool's verdicts are checked against the brute-force evaluator (:func:`evaluate` on
the whole trace; a verdict the brute force leaves unknown counts as wrong): all of ours,
a random sample of mstlo's verdicts at state times (its dense semantics also gives
verdicts at times between states; they are counted, not checked) and of reelay's. The
``BENCH mtl-progression`` compares the same work as mstlo: our every-step mode
(:meth:`StepMonitor.run` over the whole trace, a verdict per state, each with the state
that decided it) against mstlo's ``update_batch`` over the same trace, both timed from
the formula's text, interleaved, best of ``REPEAT`` (``run`` pauses Python's cycle
collector while it runs: its verdicts, named tuples, stay tracked, where mstlo's plain
tuples are not, and would trigger full collections of the heap). Every section is timed
in the process's CPU time (both tools are single-threaded; mstlo's Rust core runs in
this process, so its time is counted whole): on a shared, loaded machine the wall time
of a 0.1 s section mostly measures when the scheduler let it run, which put single
runs' ratios anywhere between 1.2 and 2; the CPU time of the same section varies by a
few percent. The detail lines give the wall-clock rates too;
``BENCH mtl-progression-until`` does the same for a formula with ``until`` nested in
``always`` (mstlo's ``φ U ψ`` needs φ at the state where ψ holds too, so ours spells that
out: the same meaning, checked against the brute force as above);
``BENCH mtl-progression-monitor`` gives our execution-monitoring mode beside both peers.
"""

from __future__ import annotations

import bisect
import gc
import random
import statistics
import time
from collections.abc import Callable
from typing import Any

from bench import fmt, progress, report
from dyknow_core.reasoning.mtl import Monitor, StepMonitor, Verdict, evaluate, parse

FORMULA = "always[0,10](speed < 30 -> eventually[0,5] on_road)"
MSTLO_FORMULA = "G[0, 10](speed < 30 -> F[0, 5](on_road > 0.5))"
# past time, read DELAY s later: at s + 5, speed as it was 5 s before and on_road within 5 s
REELAY_FORMULA = "historically[0:10]((once[5:5]{speed < 30}) -> (once[0:5]{on_road}))"
DELAY = 15.0
# until inside always; mstlo's U also needs its left side where the right one holds
UNTIL_FORMULA = "always[0,10](speed < 30 -> (speed < 35 until[0,5] (on_road and speed < 35)))"
MSTLO_UNTIL_FORMULA = "G[0, 10](speed < 30 -> ((speed < 35) U[0, 5] (on_road > 0.5)))"
N = 100_000
REPEAT = 9
CHECK = 2000  # mstlo verdicts checked against the brute force (it is O(window²) each)


def cpu_timed(fn: Callable[[], Any]) -> tuple[float, float, Any]:
    """CPU seconds (this process, every thread) and wall seconds one call took, its result."""
    w0, c0 = time.perf_counter(), time.process_time()
    result = fn()
    c1, w1 = time.process_time(), time.perf_counter()
    return c1 - c0, w1 - w0, result


def make_trace(n: int = N, seed: int = 7) -> list[tuple[float, dict[str, Any]]]:
    """States at non-uniform times: speed a bounded random walk, on_road in bursts."""
    rnd = random.Random(seed)
    t, speed, on_road = 0.0, 25.0, False
    out: list[tuple[float, dict[str, Any]]] = []
    for _ in range(n):
        out.append((t, {"speed": speed, "on_road": on_road}))
        t = round(t + rnd.uniform(0.05, 0.95), 6)
        speed = min(40.0, max(0.0, speed + rnd.gauss(0, 3)))
        if rnd.random() < 0.08:
            on_road = not on_road
    return out


def run_ours(trace: list[tuple[float, dict[str, Any]]]) -> list[Verdict]:
    """Our monitor over the whole trace: the certain verdicts, restarting after each."""
    return Monitor(FORMULA).run(trace)


def run_ours_every_step(
    trace: list[tuple[float, dict[str, Any]]], formula: str = FORMULA
) -> list[Verdict]:
    """One evaluation per state (what mstlo computes), each reported once certain."""
    return StepMonitor(formula).run(trace)


def mstlo_input(trace: list[tuple[float, dict[str, Any]]]) -> list[tuple[str, float, float]]:
    """mstlo's flat batch: (signal, value, timestamp), booleans as 0/1."""
    flat: list[tuple[str, float, float]] = []
    for t, s in trace:
        flat.append(("speed", float(s["speed"]), t))
        flat.append(("on_road", 1.0 if s["on_road"] else 0.0, t))
    return flat


def run_mstlo(
    mstlo: Any, flat: list[tuple[str, float, float]], formula: str = MSTLO_FORMULA
) -> list[tuple[float, bool]]:
    """mstlo's eager monitor over the batch: (timestamp, verdict) pairs."""
    mon = mstlo.Monitor(mstlo.parse_formula(formula), semantics="EagerQualitative")
    return list(mon.update_batch(flat).verdicts())


def reelay_input(trace: list[tuple[float, dict[str, Any]]]) -> list[dict[str, Any]]:
    """reelay's records: one dict per state with its time."""
    return [{"time": t, "speed": s["speed"], "on_road": s["on_road"]} for t, s in trace]


def run_reelay(reelay: Any, records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """reelay's dense monitor of the past-time rewrite: the change points of its value."""
    m = reelay.dense_timed_monitor(pattern=REELAY_FORMULA)
    out: list[dict[str, Any]] = []
    update = m.update
    for r in records:
        out += update(r)
    return out


def wrong_reelay(
    trace: list[tuple[float, dict[str, Any]]], changes: list[dict[str, Any]]
) -> tuple[int, int]:
    """Wrong verdicts in a random sample of starts t (read from the rewrite at t + 15)."""
    f = parse(FORMULA)
    cp_t = [c["time"] for c in changes]
    last = trace[-1][0]
    starts = [i for i, (t, _) in enumerate(trace) if t + DELAY <= last]
    sample = random.Random(2).sample(starts, min(CHECK, len(starts)))
    wrong = 0
    for i in sample:
        k = bisect.bisect_right(cp_t, trace[i][0] + DELAY) - 1
        if k < 0 or evaluate(f, trace, i) is not bool(changes[k]["value"]):
            wrong += 1
    return wrong, len(sample)


def wrong_ours(
    trace: list[tuple[float, dict[str, Any]]], verdicts: list[Verdict], formula: str = FORMULA
) -> int:
    """Our verdicts the brute force disagrees with (or leaves unknown)."""
    f = parse(formula)
    index = {t: i for i, (t, _) in enumerate(trace)}
    return sum(1 for v in verdicts if evaluate(f, trace, index[v.start]) is not v.verdict)


def wrong_mstlo(
    trace: list[tuple[float, dict[str, Any]]],
    verdicts: list[tuple[float, bool]],
    formula: str = FORMULA,
) -> tuple[int, int, int, int]:
    """Wrong verdicts in a random sample of mstlo's at state times; sample size, off-state
    verdicts (its dense semantics also decides times between states) and states without one.
    """
    f = parse(formula)
    times = [t for t, _ in trace]
    at_state: dict[int, bool] = {}
    off = 0
    for ts, v in verdicts:
        i = bisect.bisect_left(times, ts - 1e-6)
        if i < len(times) and abs(times[i] - ts) <= 1e-6:
            at_state.setdefault(i, bool(v))
        else:
            off += 1
    items = sorted(at_state.items())
    sample = random.Random(1).sample(items, min(CHECK, len(items)))
    wrong = sum(1 for i, v in sample if evaluate(f, trace, i) is not v)
    return wrong, len(sample), off, len(trace) - len(at_state)


def run() -> None:
    """Measure and print the detail and the BENCH lines."""
    trace = make_trace()
    try:
        import mstlo_python as mstlo
    except ImportError as exc:  # pragma: no cover - a dev install has it
        mstlo = None
        print(f"mstlo-python: not available ({exc}); no comparison")
    try:
        import reelay
    except ImportError as exc:  # pragma: no cover - a dev install has it
        reelay = None
        print(f"reelay: not available ({exc}); no comparison")
    flat = mstlo_input(trace) if mstlo is not None else []
    records = reelay_input(trace) if reelay is not None else []
    # (ours, mstlo's) every-step formulas: the headline line and the until line
    cases = {"mtl-progression": (FORMULA, MSTLO_FORMULA)}
    cases["mtl-progression-until"] = (UNTIL_FORMULA, MSTLO_UNTIL_FORMULA)
    times: dict[str, list[float]] = {}  # CPU seconds per run
    walls: dict[str, list[float]] = {}
    out: dict[str, Any] = {}

    def measure(key: str, fn: Any) -> None:
        gc.collect()
        d, w, out[key] = cpu_timed(fn)
        times.setdefault(key, []).append(d)
        walls.setdefault(key, []).append(w)

    for k in range(REPEAT):
        progress(f"mtl run {k + 1}/{REPEAT}")
        measure("monitor", lambda: run_ours(trace))
        for name, (ours_f, mstlo_f) in cases.items():
            measure(f"{name}/ours", lambda f=ours_f: run_ours_every_step(trace, f))
            if mstlo is not None:
                measure(f"{name}/mstlo", lambda f=mstlo_f: run_mstlo(mstlo, flat, f))
        if reelay is not None:
            measure("reelay", lambda: run_reelay(reelay, records))

    def rate(key: str) -> float:
        return N / min(times[key])

    def median(key: str) -> str:
        # the CPU median, and the best wall-clock rate (what a user of an idle machine sees)
        return f"{fmt(N / statistics.median(times[key]))}, wall best {fmt(N / min(walls[key]))}"

    progress("checking verdicts against brute force")
    ours_v: list[Verdict] = out["monitor"]
    print(
        f"ours (monitor, restart after each verdict): {fmt(rate('monitor'))} states/s "
        f"(median {median('monitor')}), {len(ours_v)} verdicts, "
        f"{wrong_ours(trace, ours_v)} wrong vs brute force"
    )
    for name, (ours_f, mstlo_f) in cases.items():
        step_v: list[Verdict] = out[f"{name}/ours"]
        sample = step_v[:: max(1, len(step_v) // CHECK)]
        print(
            f"{name}: ours {ours_f!r} (every step, StepMonitor.run): {fmt(rate(name + '/ours'))} "
            f"states/s (median {median(name + '/ours')}), {len(step_v)} verdicts, "
            f"{wrong_ours(trace, sample, ours_f)} wrong of {len(sample)} checked vs brute force"
        )
        if mstlo is not None:
            mstlo_v = out[f"{name}/mstlo"]
            w_m, checked, off, undecided = wrong_mstlo(trace, mstlo_v, ours_f)
            print(
                f"{name}: mstlo-python {mstlo.__version__} {mstlo_f!r} (EagerQualitative, "
                f"batch): {fmt(rate(name + '/mstlo'))} states/s (median "
                f"{median(name + '/mstlo')}), {len(mstlo_v)} verdicts ({off} at times between "
                f"states, {undecided} states without one), {w_m} wrong of {checked} checked "
                f"at state times vs brute force"
            )
    if reelay is not None:
        reelay_v = out["reelay"]
        w_r, checked_r = wrong_reelay(trace, reelay_v)
        print(
            f"reelay (dense, past-time rewrite read {DELAY:g} s later): {fmt(rate('reelay'))} "
            f"states/s (median {median('reelay')}), {len(reelay_v)} change points, "
            f"{w_r} wrong of {checked_r} starts checked vs brute force"
        )
    if mstlo is not None:
        # The headline compares the same work: a verdict for every state, as mstlo gives.
        # Our restart monitor (one verdict per evaluation) is reported apart, so a ratio
        # between different jobs is never the one quoted.
        for name in cases:
            report(
                name,
                rate(name + "/ours"),
                "mstlo",
                rate(name + "/mstlo"),
                "states/s",
                better="higher",
            )
        m = rate("mtl-progression/mstlo")
        report("mtl-progression-monitor", rate("monitor"), "mstlo", m, "states/s", better="higher")
    if reelay is not None:
        report(
            "mtl-progression-monitor",
            rate("monitor"),
            "reelay",
            rate("reelay"),
            "states/s",
            better="higher",
        )


if __name__ == "__main__":
    run()
