from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock
from dyknow_core._exceptions import ProcessError
from dyknow_core.reasoning.mtl import (
    Always,
    And,
    BoolConst,
    Compare,
    Eventually,
    Feature,
    Implies,
    Monitor,
    MonitorProcess,
    MTLSyntaxError,
    Not,
    Or,
    Quantifier,
    Residual,
    StepMonitor,
    Until,
    Var,
    _engine,
    add_monitor,
    domains,
    evaluate,
    features,
    parse,
    progress,
)

FORMULA = "always[0,10](speed < 30 -> eventually[0,5] on_road)"

# -- parser ---------------------------------------------------------------------------------


def test_parse_each_construct() -> None:
    assert parse("on_road") == Feature("on_road")
    assert parse("true") == BoolConst(True)
    assert parse("speed < 30") == Compare("<", Feature("speed"), 30)
    assert parse("30.5 >= speed") == Compare(">=", 30.5, Feature("speed"))
    assert parse('kind == "car"') == Compare("==", Feature("kind"), "car")
    assert parse("flag != false") == Compare("!=", Feature("flag"), False)
    assert parse("x <= -2") == Compare("<=", Feature("x"), -2)
    assert parse("a > b") == Compare(">", Feature("a"), Feature("b"))
    assert parse("not p") == Not(Feature("p"))
    assert parse("p and q or r") == Or(And(Feature("p"), Feature("q")), Feature("r"))
    assert parse("p -> q -> r") == Implies(Feature("p"), Implies(Feature("q"), Feature("r")))
    assert parse("p implies q") == Implies(Feature("p"), Feature("q"))
    assert parse("always[0,10] p") == Always(0.0, 10.0, Feature("p"))
    assert parse("eventually p") == Eventually(0.0, math.inf, Feature("p"))
    assert parse("eventually[1.5, inf] p") == Eventually(1.5, math.inf, Feature("p"))
    assert parse("p until[0,3] q") == Until(0.0, 3.0, Feature("p"), Feature("q"))
    assert parse("always p and q") == And(Always(0.0, math.inf, Feature("p")), Feature("q"))
    f = parse("forall x in Cars: speed(x) < 30")
    assert f == Quantifier(True, "x", "Cars", Compare("<", Feature("speed", (Var("x"),)), 30))
    g = parse('exists x in Cars: exists y in Cars: near(x, y) and speed("car1") > 2')
    assert isinstance(g, Quantifier) and not g.universal
    assert features(g) == ["near", "speed"] and domains(g) == ["Cars"]
    assert features(FORMULA) == ["speed", "on_road"]
    # printing round-trips
    for text in [FORMULA, "p until[0,3] (q or not r)", str(g), "always (a -> eventually b)"]:
        assert parse(str(parse(text))) == parse(text)


@pytest.mark.parametrize(
    ("text", "line", "column"),
    [
        ("always[0,10](speed < 30 -> )", 1, 28),
        ("p and\n  q <", 2, 6),
        ("always[5,1] p", 1, 8),
        ("p $ q", 1, 3),
        ("(p and q", 1, 9),
        ("speed(x) > 1", 1, 7),
        ("forall x in D: x", 1, 16),
        ("p q", 1, 3),
        ("1 < 2", 1, 3),
        ("eventually[a,2] p", 1, 12),
    ],
)
def test_syntax_errors_point_at_line_and_column(text: str, line: int, column: int) -> None:
    with pytest.raises(MTLSyntaxError) as e:
        parse(text)
    assert (e.value.line, e.value.column) == (line, column), str(e.value)
    assert f"line {line}, column {column}" in str(e.value)


def test_a_misspelt_operator_is_named() -> None:
    with pytest.raises(MTLSyntaxError, match="'eventualy' is not an operator") as e:
        parse("always[0,10](speed < 30 -> eventualy[0,5] on_road)")
    assert "did you mean 'eventually'?" in str(e.value) and e.value.column == 28


# -- progression -------------------------------------------------------------------------------


def test_violation_is_reported_as_soon_as_certain() -> None:
    m = Monitor(FORMULA)
    assert m.step(0.0, {"speed": 10, "on_road": False}) is None
    for k in range(1, 5):
        assert m.step(float(k), {"speed": 50, "on_road": False}) is None
    # the obligation from t=0 ends at 5: the state at 5 is its last chance
    v = m.step(5.0, {"speed": 50, "on_road": False})
    assert v is not None and v.verdict is False and (v.start, v.time) == (0.0, 5.0)
    # without a state at 5, the first state after it decides
    m = Monitor(FORMULA)
    m.step(0.0, {"speed": 10, "on_road": False})
    v = m.step(5.5, {"speed": 50, "on_road": True})
    assert v is not None and v.verdict is False and (v.start, v.time) == (0.0, 5.5)


def test_violation_is_certain_at_once_with_dt_next() -> None:
    r = progress("eventually[0,5] p", {"p": False}, 0.0)
    assert isinstance(r, Residual)
    assert progress(r, {"p": False}, 4.0, dt_next=2.0) is False
    assert progress("eventually[0,5] p", {"p": False}, 0.0, dt_next=6.0) is False
    assert progress("always[0,5] p", {"p": True}, 0.0, dt_next=6.0) is True
    assert progress("p until[0,5] q", {"p": True, "q": False}, 0.0, dt_next=6.0) is False


def test_satisfaction_and_restart() -> None:
    m = Monitor("always[0,2] p")
    verdicts = m.run([(float(t), {"p": t not in (4, 9)}) for t in range(12)])
    assert [(v.start, v.time, v.verdict) for v in verdicts] == [
        (0.0, 2.0, True),  # the state at 2 is the window's last
        (3.0, 4.0, False),
        (5.0, 7.0, True),
        (8.0, 9.0, False),
    ]
    assert m.step(13.0, {"p": True}) == (10.0, 13.0, True)  # window [10,12] closed by 13
    unbounded = Monitor("always not (running_a and running_b)")
    trace = [(float(t), {"running_a": True, "running_b": t in (2, 3, 7)}) for t in range(10)]
    assert [(v.time, v.verdict) for v in unbounded.run(trace)] == [
        (2.0, False),
        (3.0, False),
        (7.0, False),
    ]


def test_progression_simplifies_pending_obligations() -> None:
    m = Monitor(FORMULA)
    for k in range(50):
        m.step(k * 0.1, {"speed": 10, "on_road": False})
    # fifty pending eventually obligations collapse into one, beside the always
    assert str(m.residual).count("eventually") == 1


def test_quantifiers_over_the_members_in_the_state() -> None:
    f = "forall x in Cars: eventually[0,2] speed(x) < 30"
    s0 = {"Cars": ["c1", "c2"], "speed": {"c1": 10, "c2": 40}}
    s1 = {"Cars": ["c1", "c2"], "speed": {"c1": 40, "c2": 20}}
    assert Monitor(f).run([(0.0, s0), (1.0, s1)]) == [(0.0, 1.0, True)]
    assert evaluate(f, [(0.0, s0), (1.0, s1)]) is True
    e = "exists x in Cars: speed(x) > 100"
    assert progress(e, s0, 0.0) is False and progress(e, {"Cars": []}, 0.0) is False
    assert progress("forall x in Cars: speed(x) > 100", {}, 0.0) is True


def test_missing_and_incomparable_values_make_atoms_false() -> None:
    assert progress("speed < 30", {"speed": None}, 0.0) is False
    assert progress("speed < 30", {"speed": "fast"}, 0.0) is False
    assert progress("not speed < 30", {}, 0.0) is True
    assert progress("on_road", {"on_road": 1}, 0.0) is False


def test_step_monitor_gives_one_verdict_per_state() -> None:
    sm = StepMonitor("eventually[0,1] p")
    out = []
    for t, p in [(0.0, False), (0.5, False), (1.2, True), (3.0, False)]:
        out += sm.step(t, {"p": p})
    assert sorted((v.start, v.verdict) for v in out) == [(0.0, False), (0.5, True), (1.2, True)]
    assert sm.undecided() == [3.0]


# -- progression against brute force ----------------------------------------------------------

_atoms = st.sampled_from(["p", "q", "x < 1", "x >= 2", "not p"])
_bounds = st.tuples(st.sampled_from([0, 0.5, 1, 2]), st.sampled_from([0, 0.5, 1, 2.5, "inf"]))


def _iv(b: tuple[Any, Any]) -> str:
    lo, hi = b
    if hi != "inf" and hi < lo:
        lo, hi = hi, lo
    return f"[{lo},{hi}]"


def _formulas() -> st.SearchStrategy[str]:
    def extend(children: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
        return st.one_of(
            st.builds(lambda a: f"not ({a})", children),
            st.builds(lambda a, b: f"({a}) and ({b})", children, children),
            st.builds(lambda a, b: f"({a}) or ({b})", children, children),
            st.builds(lambda a, b: f"({a}) -> ({b})", children, children),
            st.builds(lambda i, a: f"always{_iv(i)} ({a})", _bounds, children),
            st.builds(lambda i, a: f"eventually{_iv(i)} ({a})", _bounds, children),
            st.builds(lambda a, i, b: f"({a}) until{_iv(i)} ({b})", children, _bounds, children),
            st.builds(lambda a: f"forall c in D: ({a}) and v(c) > 0", children),
            st.builds(lambda a: f"exists c in D: ({a}) or v(c) > 1", children),
        )

    base = st.one_of(_atoms, st.sampled_from(["true", "false"]))
    return st.recursive(base, extend, max_leaves=6)


_states = st.fixed_dictionaries(
    {
        "p": st.booleans(),
        "q": st.booleans(),
        "x": st.integers(0, 3),
        "D": st.lists(st.sampled_from(["a", "b"]), max_size=2, unique=True),
        "v": st.fixed_dictionaries({"a": st.integers(0, 2), "b": st.integers(0, 2)}),
    }
)
_traces = st.lists(
    st.tuples(st.sampled_from([0.25, 0.5, 1.0, 1.5]), _states), min_size=1, max_size=8
).map(lambda steps: [(sum(d for d, _ in steps[: k + 1]), s) for k, (_, s) in enumerate(steps)])


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_formulas(), _traces)
def test_progression_agrees_with_brute_force(text: str, trace: list[Any]) -> None:
    f = parse(text)
    # from every start: the residual is decided exactly when the brute force is certain
    for i in range(len(trace)):
        r: Any = f
        for k in range(i, len(trace)):
            if isinstance(r, bool):
                break
            r = progress(r, trace[k][1], trace[k][0])
            expected = evaluate(f, trace[: k + 1], i)
            got = r if isinstance(r, bool) else None
            assert got == expected, (text, i, k, str(r))
    # the monitor's verdicts agree with the brute force on the whole trace
    for v in Monitor(f).run(trace):
        start = next(j for j, (t, _) in enumerate(trace) if t == v.start)
        assert evaluate(f, trace, start) is v.verdict


@settings(max_examples=300, deadline=None)
@given(_formulas(), _traces)
def test_every_step_agrees_with_brute_force(text: str, trace: list[Any]) -> None:
    f = parse(text)
    sm = StepMonitor(f)
    for k, (t, s) in enumerate(trace):
        for v in sm.step(t, s):
            start = next(j for j, (tj, _) in enumerate(trace) if tj == v.start)
            # decided at k, exactly when the brute force on the prefix becomes certain
            assert evaluate(f, trace[: k + 1], start) is v.verdict, (text, start, k)
            assert k == 0 or trace[k - 1][0] < v.start or (evaluate(f, trace[:k], start) is None)
    for start in sm.undecided():
        i = next(j for j, (tj, _) in enumerate(trace) if tj == start)
        assert evaluate(f, trace, i) is None


@settings(max_examples=300, deadline=None)
@given(_formulas(), _traces)
def test_dt_next_decides_what_the_next_state_would(text: str, trace: list[Any]) -> None:
    f = parse(text)
    for i in range(len(trace) - 1):
        r: Any = f
        for k in range(i, len(trace) - 1):
            t = trace[k][0]
            r = progress(r, trace[k][1], t, dt_next=trace[k + 1][0] - t)
            if isinstance(r, bool):
                # only windows that end before the next state were closed
                assert evaluate(f, trace[: k + 2], i) is r, (text, i, k)
                break


# -- in an instance ---------------------------------------------------------------------------


def test_add_monitor_publishes_verdicts() -> None:
    clock = ManualClock()
    inst = DyKnowInstance(clock=clock)
    speed = inst.add_source("car/speed")
    road = inst.add_source("car/on_road")
    proc = add_monitor(
        inst,
        "always[0,2] (speed < 30 -> on_road)",
        label="alerts",
        components={"speed": "car/speed", "on_road": "car/on_road"},
        period=1.0,
    )
    assert isinstance(proc, MonitorProcess)
    assert inst.processes[proc.name] is proc and inst.has_label("alerts/state")
    got: list[Any] = []
    inst.subscribe("alerts", callback=got.extend)
    for k, (v, r) in enumerate([(10, True), (40, False), (10, True), (10, False), (10, True)]):
        speed.push(v, valid_time=k * NS_PER_S, available_time=k * NS_PER_S)
        road.push(r, valid_time=k * NS_PER_S, available_time=k * NS_PER_S)
    verdicts = [(value["verdict"], tv // NS_PER_S) for value, tv, _ in got]
    # start 0 is decided by the window's last state (2); the restart at 3 fails at once
    assert verdicts == [(True, 2), (False, 3)]
    assert [value["start"] for value, _, _ in got] == [0, 3 * NS_PER_S]
    assert got[0][0]["formula"] == "always[0,2] (speed < 30 -> on_road)"
    assert proc.describe()["verdicts"] == len(got)
    inst.remove_process(proc.name)
    assert not inst.has_label("alerts") and not inst.has_label("alerts/state")


def test_add_monitor_defaults_to_feature_labels() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    p = inst.add_source("p")
    proc = add_monitor(inst, "always not p", period=1.0)
    got: list[Any] = []
    inst.subscribe(proc.label, callback=got.extend)
    for k, v in enumerate([False, True, False, True]):
        p.push(v, valid_time=k * NS_PER_S, available_time=k * NS_PER_S)
    assert [(val["verdict"], tv // NS_PER_S) for val, tv, _ in got] == [(False, 1), (False, 3)]
    with pytest.raises(ProcessError):
        add_monitor(inst, "true")


def test_add_monitor_with_a_dynamic_domain() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    cars = inst.add_source("cars")
    speed = inst.add_source("car/speed")
    proc = add_monitor(
        inst,
        "forall c in Cars: speed(c) < 30",
        components={"Cars": "cars", "speed": "car/speed"},
    )
    got: list[Any] = []
    inst.subscribe(proc.label, callback=got.extend)
    steps = [(["c1"], {"c1": 10}), (["c1", "c2"], {"c1": 10, "c2": 40}), (["c1"], {"c1": 5})]
    for k, (members, speeds) in enumerate(steps):
        cars.push(members, valid_time=k * NS_PER_S, available_time=k * NS_PER_S)
        speed.push(speeds, valid_time=k * NS_PER_S, available_time=k * NS_PER_S)
    # no temporal operator: a verdict per state
    assert [(v["verdict"], tv // NS_PER_S) for v, tv, _ in got] == [
        (True, 0),
        (False, 1),
        (True, 2),
    ]


# -- command line ----------------------------------------------------------------------------


def _write(tmp_path: Path, lines: list[str]) -> str:
    path = tmp_path / "trace.jsonl"
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def monitor_main(args: list[str]) -> int:
    """``dyknow monitor ARGS`` in this process; the exit code."""
    from federation.cli import main

    return main(["monitor", *args])


def test_cli_prints_verdicts(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trace = _write(
        tmp_path,
        [json.dumps({"t": t, "p": t != 2}) for t in range(5)],
    )
    assert monitor_main(["always[0,1] p", "--trace", trace]) == 0
    out = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert out == [
        {"t": 1, "from": 0, "verdict": True},
        {"t": 2, "from": 2, "verdict": False},
        {"t": 4, "from": 3, "verdict": True},
    ]
    assert monitor_main(["eventually[0,1] p", "--trace", trace, "--every-step"]) == 0
    out = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [(o["t"], o["verdict"]) for o in out] == [
        (0, True),
        (1, True),
        (2, True),
        (3, True),
        (4, True),
    ]


def test_cli_reports_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trace = _write(tmp_path, ['{"t": 0, "p": true}', "{oops", '{"t": 1}'])
    assert monitor_main(["p", "--trace", trace]) == 2
    err = capsys.readouterr().err
    assert "line 2" in err and "Traceback" not in err
    trace = _write(tmp_path, ['{"t": 0, "p": true}', '{"t": 1, "q": true}'])
    assert monitor_main(["always p", "--trace", trace]) == 2
    assert "line 2" in capsys.readouterr().err
    assert monitor_main(["speed <", "--trace", trace]) == 2
    assert "column" in capsys.readouterr().err
    assert monitor_main(["p", "--trace", str(tmp_path / "missing.jsonl")]) == 2
    trace = _write(tmp_path, ['{"t": 1, "p": true}', '{"t": 1, "p": true}'])
    assert monitor_main(["p", "--trace", trace]) == 2
    assert "line 2" in capsys.readouterr().err


def test_cli_names_a_value_of_the_wrong_type(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def err(formula: str, *states: dict[str, Any]) -> str:
        trace = _write(tmp_path, [json.dumps({"t": t, **s}) for t, s in enumerate(states)])
        assert monitor_main([formula, "--trace", trace]) == 2
        return capsys.readouterr().err.strip()

    ok = {"speed": 20, "p": True, "name": "a", "Cars": ["c1"], "v": {"c1": 1.5}}
    assert err("always speed < 30", ok, {**ok, "speed": "31"}).endswith(
        "line 2: 'speed' is a string ('31'), expected a number"
    )
    assert err("always p", ok, ok, {**ok, "p": 1}).endswith(
        "line 3: 'p' is a number (1), expected true or false"
    )
    assert err("name == 'a' or name == 2", ok, {**ok, "name": [1]}).endswith(
        "line 2: 'name' is an array ([1]), expected a number or a string"
    )
    bad = {**ok, "v": {"c1": True}}
    assert err("forall c in Cars: v(c) > 1", ok, bad).endswith(
        "line 2: 'v'['c1'] is true or false (True), expected a number"
    )
    assert "line 1: 'Cars' is a number" in err("exists c in Cars: v(c) > 1", {**ok, "Cars": 3})
    trace = _write(tmp_path, [json.dumps({"t": 0, **ok, "speed": None, "p": None})])
    assert monitor_main(["p or speed < 30 or name == p", "--trace", trace]) == 0  # null: no value


def test_dyknow_command(tmp_path: Path) -> None:
    trace = _write(tmp_path, [json.dumps({"t": t, "speed": 20 + 5 * t}) for t in range(4)])
    exe = Path(sys.executable).with_name("dyknow")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "federation.cli"]
    done = subprocess.run(
        [*cmd, "monitor", "always speed < 30", "--trace", trace],
        capture_output=True,
        text=True,
        timeout=30,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])},
    )
    assert done.returncode == 0, done.stderr
    assert [json.loads(line) for line in done.stdout.splitlines()] == [
        {"t": 2, "from": 0, "verdict": False},
        {"t": 3, "from": 3, "verdict": False},
    ]
    bad = subprocess.run(
        [*cmd, "monitor", "always speed <", "--trace", trace],
        capture_output=True,
        text=True,
        timeout=30,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])},
    )
    assert bad.returncode == 2 and "Traceback" not in bad.stderr


def _fast_formulas() -> st.SearchStrategy[str]:
    bounds = st.tuples(st.sampled_from([0, 0.5, 1, 2]), st.sampled_from([0, 0.5, 1, 1.5, 2.5]))

    def extend(children: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
        return st.one_of(
            st.builds(lambda a: f"not ({a})", children),
            st.builds(lambda a, b: f"({a}) and ({b})", children, children),
            st.builds(lambda a, b: f"({a}) or ({b})", children, children),
            st.builds(lambda a, b: f"({a}) -> ({b})", children, children),
            st.builds(lambda i, a: f"always{_iv(i)} ({a})", bounds, children),
            st.builds(lambda i, a: f"eventually{_iv(i)} ({a})", bounds, children),
        )

    base = st.one_of(_atoms, st.sampled_from(["true", "false"]))
    return st.recursive(base, extend, max_leaves=7)


_long_traces = st.lists(
    st.tuples(st.sampled_from([0.25, 0.5, 0.75, 1.0, 1.5, 3.0]), _states), min_size=1, max_size=14
).map(lambda steps: [(sum(d for d, _ in steps[: k + 1]), s) for k, (_, s) in enumerate(steps)])


@settings(max_examples=800, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_fast_formulas(), _long_traces)
def test_every_step_fast_path_matches_progression_exactly(text: str, trace: list[Any]) -> None:
    f = parse(text)
    fast = StepMonitor(f)
    assert fast._fast is not None
    slow = StepMonitor(f)
    slow._fast = None  # the progression path, as for formulas outside the fragment
    compacting = StepMonitor(f)  # forgets decided positions at every step
    for k, (t, s) in enumerate(trace):
        compacting._compact_at = 0
        got, want = fast.step(t, s), slow.step(t, s)
        assert got == want, (text, k)
        assert compacting.step(t, s) == want, (text, k)
        for v in got:
            start = next(j for j, (tj, _) in enumerate(trace) if tj == v.start)
            assert evaluate(f, trace[: k + 1], start) is v.verdict, (text, start, k)
    assert fast.undecided() == slow.undecided() == compacting.undecided()
    for start in fast.undecided():
        i = next(j for j, (tj, _) in enumerate(trace) if tj == start)
        assert evaluate(f, trace, i) is None


def _until_formulas() -> st.SearchStrategy[str]:
    # bounds on the traces' quarter-second grid, so windows often end exactly at a state
    bounds = st.tuples(st.sampled_from([0, 0.25, 0.5, 1, 2]), st.sampled_from([0, 0.5, 1, 1.5]))
    pure = st.recursive(
        st.one_of(_atoms, st.sampled_from(["true", "false"])),
        lambda c: st.one_of(
            st.builds(lambda a: f"not ({a})", c),
            st.builds(lambda a, b: f"({a}) and ({b})", c, c),
            st.builds(lambda a, b: f"({a}) or ({b})", c, c),
        ),
        max_leaves=2,
    )
    until = st.builds(lambda a, i, b: f"({a}) until{_iv(i)} ({b})", pure, bounds, pure)

    def extend(children: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
        return st.one_of(
            st.builds(lambda a: f"not ({a})", children),
            st.builds(lambda a, b: f"({a}) and ({b})", children, children),
            st.builds(lambda a, b: f"({a}) -> ({b})", children, children),
            st.builds(lambda i, a: f"always{_iv(i)} ({a})", bounds, children),
            st.builds(lambda i, a: f"eventually{_iv(i)} ({a})", bounds, children),
        )

    return st.recursive(st.one_of(until, _atoms), extend, max_leaves=4)


@settings(max_examples=800, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_until_formulas(), _long_traces)
def test_every_step_until_matches_progression_at_window_edges(text: str, trace: list[Any]) -> None:
    f = parse(text)
    fast = StepMonitor(f)
    assert fast._fast is not None
    slow = StepMonitor(f)
    slow._fast = None
    compacting = StepMonitor(f)
    stepped = []
    for k, (t, s) in enumerate(trace):
        compacting._compact_at = 0
        got, want = fast.step(t, s), slow.step(t, s)
        assert got == want, (text, k)
        assert compacting.step(t, s) == want, (text, k)
        stepped += got
        for v in got:
            start = next(j for j, (tj, _) in enumerate(trace) if tj == v.start)
            assert evaluate(f, trace[: k + 1], start) is v.verdict, (text, start, k)
    assert fast.undecided() == slow.undecided() == compacting.undecided()
    for start in fast.undecided():
        i = next(j for j, (tj, _) in enumerate(trace) if tj == start)
        assert evaluate(f, trace, i) is None
    assert StepMonitor(f).run(trace) == stepped  # the batch form gives the same, in order


_values = st.sampled_from([None, 0, 1, 2, 0.5, 1.5, -0.0, math.nan, math.inf, "a", True, False])
_pure_atoms = st.sampled_from(
    ["p", "x < 1.5", "x >= 1", "x == 2", "x != 0.5", "x > y", "x <= 2", "not x < 1", "2 > x"]
)


@settings(max_examples=400, deadline=None)
@given(
    st.recursive(
        st.one_of(_pure_atoms, st.sampled_from(["true", "false"])),
        lambda c: st.one_of(
            st.builds(lambda a: f"not ({a})", c),
            st.builds(lambda a, b: f"({a}) and ({b})", c, c),
            st.builds(lambda a, b: f"({a}) or ({b})", c, c),
            st.builds(lambda a, b: f"({a}) -> ({b})", c, c),
        ),
        max_leaves=4,
    ),
    st.lists(st.fixed_dictionaries({"p": _values, "x": _values, "y": _values}), max_size=6),
)
def test_every_step_state_formulas_agree_with_progression(text: str, states: list[Any]) -> None:
    # the every-step engine writes comparisons out: missing, odd and non-float values too
    f = parse(text)
    sm = StepMonitor(f)
    for k, s in enumerate(states):
        got = sm.step(float(k), s)
        assert [v.verdict for v in got] == [progress(f, s, float(k))], (text, s)


@settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(_fast_formulas(), _until_formulas()), _long_traces, st.integers(0, 14))
def test_monitor_run_matches_stepping(text: str, trace: list[Any], cut: int) -> None:
    # run reads the restarting verdicts off the every-step engine; step progresses
    f = parse(text)
    stepped, ran = Monitor(f), Monitor(f)
    want = [v for v in (stepped.step(t, s) for t, s in trace) if v is not None]
    compact = _engine._COMPACT
    _engine._COMPACT = 1 + cut % 3  # forget decided positions every state or few
    try:
        got = ran.run(trace[:cut])
    finally:
        _engine._COMPACT = compact
    # the evaluation left open goes on by step, as if run had stepped
    got += [v for v in (ran.step(t, s) for t, s in trace[cut:]) if v is not None]
    assert got == want, text
    assert (ran.residual is None) == (stepped.residual is None)


def test_a_member_named_with_a_dot_wins_even_when_null() -> None:
    """``"a.b"`` present (even null) is that member, not the field ``b`` of ``a``."""
    state = {"m": {"a.b": None, "a": {"b": 5}}}
    assert evaluate('m("a.b") > 3', [(0.0, state)]) is not True
    assert evaluate('m("a.b") > 3', [(0.0, {"m": {"a": {"b": 5}}})]) is True


def test_a_superscript_digit_in_a_path_reads_nothing() -> None:
    """``ranges.²``: no index (``"²".isdigit()`` but ``int`` refuses it), not an error."""
    state = {"m": {"ranges": [7, 8, 9]}}
    assert evaluate('m("ranges.²") > 3', [(0.0, state)]) is not True
    assert evaluate('m("ranges.2") > 3', [(0.0, state)]) is True
