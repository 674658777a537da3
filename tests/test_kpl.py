"""KPL: parsing every construct, errors with line/column, setup on an instance, the CLI."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock
from dyknow_core.kpl import (
    AnchoringDecl,
    ChangesDecl,
    ChronicleDecl,
    ClassDecl,
    CUDecl,
    KPLCheckError,
    KPLSetupError,
    LinkDecl,
    MonitorDecl,
    SourceDecl,
    StateDecl,
    StreamDecl,
    check,
    parse,
    setup,
)
from dyknow_core.reasoning import Anchoring, ObjectClass, add_anchoring
from federation.cli import main as dyknow_main

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "traffic.kpl"

FULL = """\
# every construct
source car5/speed cache {max_samples: 100, max_age: 10}
source car5/offset
cu smoother = examples.kpl_functions:make_smoother(alpha=0.3)
    inputs car5/speed with {lower: 0, upper: 250, max_delay: 0.3, change: absolute(0.5)},
           car5/offset
    output car5/speed_smooth
cu road = examples.kpl_functions:on_road inputs car5/offset output car5/on_road
stream car5/slow = car5/speed with {sample_period: 1, approximation: linear}
state car5/state = {speed: car5/speed, on_road: car5/on_road}
    every 0.5 latest max_delay 0.2 missing last
changes car5/on_road
changes car5/speed by absolute(5)
monitor speeding = "always[0,10](speed < 30 -> eventually[0,5] on_road)" every 1
    max_delay 0.5 with {speed: car5/speed, on_road: car5/on_road} output alerts/speeding
chronicle left_road {
    input on_road = events/changed/car5/on_road
    event leave = on_road(car) from true to false
    event back = on_road(car) from false to true
    constraint leave -> back in [0, 30]
    forbidden on_road(car) between leave and back
    forbidden on_road after back in [0, 5]
    output chronicles/left
}
class Car {
    feature speed = "car/{id}/speed"
    prefix car
    create "speed > 0" from car5/speed
    maintain "eventually[0,5] speed > 0"
    codesignate "a_speed == b_speed" continuous
    relation near = examples.kpl_functions:on_road
}
class FastCar { base Car  add "always[0,3] speed > 30" }
link Follows {
    from Car to FastCar
    establish "speed > 50"
    reestablish "a_speed < b_speed"
    maintain "eventually[0,10] a_speed < b_speed"
    compute examples.kpl_functions:on_road
}
anchoring every 0.5 output events/cars
"""


def errors(text: str, known: tuple[str, ...] = ()) -> list[tuple[int, int, str]]:
    return [(e.line, e.column, e.message) for e in check(text, known)]


# -- parsing ----------------------------------------------------------------------------------


def test_parse_every_construct() -> None:
    prog = parse(FULL)
    kinds = [type(d) for d in prog.decls]
    assert kinds == [
        SourceDecl, SourceDecl, CUDecl, CUDecl, StreamDecl, StateDecl, ChangesDecl,
        ChangesDecl, MonitorDecl, ChronicleDecl, ClassDecl, ClassDecl, LinkDecl, AnchoringDecl,
    ]  # fmt: skip
    src = prog.decls[0]
    assert isinstance(src, SourceDecl) and src.label == "car5/speed" and src.pos == (2, 1)
    assert src.cache is not None and src.cache.as_dict() == {"max_samples": 100, "max_age": 10}
    cu = prog.decls[2]
    assert isinstance(cu, CUDecl)
    assert (cu.name, cu.module, cu.attr) == ("smoother", "examples.kpl_functions", "make_smoother")
    assert cu.args is not None and cu.args.as_dict() == {"alpha": 0.3}
    assert [i.ref.label for i in cu.inputs] == ["car5/speed", "car5/offset"]
    pol = cu.inputs[0].policy
    assert pol is not None
    assert pol.as_dict() == {"lower": 0, "upper": 250, "max_delay": 0.3, "change": "absolute(0.5)"}
    assert cu.inputs[1].policy is None and cu.output.label == "car5/speed_smooth"
    road = prog.decls[3]
    assert isinstance(road, CUDecl) and road.args is None
    st = prog.decls[4]
    assert isinstance(st, StreamDecl) and st.source.label == "car5/speed"
    assert st.policy is not None
    assert st.policy.as_dict() == {"sample_period": 1, "approximation": "linear"}
    state = prog.decls[5]
    assert isinstance(state, StateDecl)
    assert state.components.as_dict() == {"speed": "car5/speed", "on_road": "car5/on_road"}
    assert state.policy.as_dict() == {
        "period": 0.5, "strategy": "latest", "max_delay": 0.2, "missing": "last",
    }  # fmt: skip
    ch = prog.decls[7]
    assert isinstance(ch, ChangesDecl) and ch.change == "absolute(5)"
    assert ch.label == "events/changed/car5/speed"
    mon = prog.decls[8]
    assert isinstance(mon, MonitorDecl)
    assert mon.formula == "always[0,10](speed < 30 -> eventually[0,5] on_road)"
    assert (mon.period, mon.max_delay, mon.label) == (1, 0.5, "alerts/speeding")
    chron = prog.decls[9]
    assert isinstance(chron, ChronicleDecl) and chron.label == "chronicles/left"
    assert chron.events[0] == {
        "name": "leave", "event": "on_road", "args": ["car"], "from": True, "to": False,
    }  # fmt: skip
    assert chron.constraints == [{"start": "leave", "end": "back", "lo": 0, "hi": 30}]
    assert chron.forbidden[0]["end"] == "back"
    assert (chron.forbidden[1]["lo"], chron.forbidden[1]["hi"]) == (0, 5)
    assert {k: r.label for k, r in chron.inputs.items()} == {
        "on_road": "events/changed/car5/on_road"
    }
    car, fast, follows, anch = prog.decls[10:]
    assert isinstance(car, ClassDecl) and car.name == "Car" and car.pos == (25, 1)
    assert car.features.as_dict() == {"speed": "car/{id}/speed"}
    assert car.fields.as_dict() == {
        "prefix": "car", "create": "speed > 0", "create_from": "car5/speed",
        "maintain": "eventually[0,5] speed > 0", "codesignate": "a_speed == b_speed",
        "codesignation": "continuous",
    }  # fmt: skip
    near = car.relations["near"]
    assert (near.module, near.attr, near.pos) == ("examples.kpl_functions", "on_road", (31, 21))
    assert isinstance(fast, ClassDecl)
    assert fast.fields.as_dict() == {"base": "Car", "add": "always[0,3] speed > 30"}
    assert isinstance(follows, LinkDecl) and follows.compute is not None
    assert follows.fields.as_dict() == {
        "from_class": "Car", "to_class": "FastCar", "establish": "speed > 50",
        "reestablish": "a_speed < b_speed", "maintain": "eventually[0,10] a_speed < b_speed",
    }  # fmt: skip
    assert follows.fields.where("establish") == (36, 5)
    assert isinstance(anch, AnchoringDecl)
    assert (anch.period, anch.output) == (0.5, "events/cars")
    assert check(FULL) == []


def test_quoted_labels_comments_and_unbounded_intervals() -> None:
    text = 'source "odd label" # a comment\nstream x = "odd label"\n'
    prog = parse(text)
    assert isinstance(prog.decls[1], StreamDecl) and prog.decls[1].source.label == "odd label"
    assert check(text) == []
    chron = parse(
        "chronicle c { event a = e\n event b = e\n constraint a -> b in [-inf, inf] }"
    ).decls[0]
    assert isinstance(chron, ChronicleDecl)
    assert chron.constraints == [{"start": "a", "end": "b", "lo": None, "hi": None}]


async def test_the_example_file_and_the_docs_example_check_and_set_up() -> None:
    assert check(EXAMPLE.read_text()) == []
    doc = (ROOT / "docs" / "kpl.md").read_text()
    block = doc.split("```kpl\n", 1)[1].split("```", 1)[0]
    assert check(block) == []
    # opened: the state's max_delay needs the instance's task group for its timer
    async with DyKnowInstance(clock=ManualClock()) as inst:
        app = setup(inst, EXAMPLE.read_text())
        assert len(app.processes) == 10 and inst.has_label("monitors/speeding")
        assert app.processes[-1] == "anchoring" and app.unsupported == []
        assert inst.has_label("events/anchoring")
        app.remove()
        assert inst.processes == {} and not inst.has_label("events/anchoring")


# -- errors ------------------------------------------------------------------------------------


def test_syntax_errors_have_line_and_column_and_recover() -> None:
    text = "source a\ncu x = m:f inputs a outptu b\nsource\nstream c = a\nbogus 3\n"
    got = errors(text)
    assert got[0][:2] == (2, 21) and "expected ',' or 'output'" in got[0][2]
    assert got[1][:2] == (4, 1) and "expected a label" in got[1][2]  # 'source' at end of line 3
    assert got[2][:2] == (5, 1) and "expected a declaration" in got[2][2]
    assert len(got) == 3  # parsing resumed at each declaration: 'stream c = a' is fine
    err = check(text)[0]
    assert err.excerpt.splitlines()[1].index("^") == 2 + 20
    assert str(err).startswith("line 2, column 21: ")
    assert err.format("f.kpl").startswith("f.kpl:2:21: ")


def test_lexical_errors() -> None:
    assert errors('source a\nsource "open\n') [0][:2] == (2, 8)  # fmt: skip
    assert errors("source a\n  source @b\n")[0] == (2, 10, "unexpected character '@'")


def test_a_number_with_a_unit_is_named_once() -> None:
    text = "source a\nstream b = a with {max_delay: 300ms}\nstate s = {a: a} every 1s latest\n"
    assert errors(text) == [
        (2, 31, "'300ms': a number takes no unit (durations are in seconds)"),
        (3, 24, "'1s': a number takes no unit (durations are in seconds)"),
    ]


def test_a_misspelt_declaration_after_a_state_is_named_as_such() -> None:
    text = 'source a\nstate s = {x: a} every 1 latest\nmoniter m = "x > 1" every 1\n'
    assert errors(text)[0] == (
        3,
        1,
        "unknown state clause 'moniter' (expected latest, closest, interpolate, strategy, "
        "max_delay, missing, start, end); or a misspelt declaration keyword, 'monitor'?",
    )


def test_unknown_policy_fields_and_impossible_policies() -> None:
    text = (
        "source a\n"
        "stream b = a with {sample_perod: 1}\n"
        "stream c = a with {lower: 5, upper: 1}\n"
        "stream d = a with {approximation: linear}\n"
        "stream e = a with {max_delay: -1}\n"
        "source f cache {max_samples: 0}\n"
        "state s = {x: a} every 0 missing maybe\n"
        "stream g = a with {change: absolute(1), change: any_change}\n"
        "changes a by relative\n"
    )
    got = errors(text)
    assert got[0][:2] == (2, 20) and "unknown policy field 'sample_perod'" in got[0][2]
    assert got[1][:2] == (3, 20) and "lower bound 5.0 is above upper 1.0" in got[1][2]
    assert got[2][:2] == (4, 20) and "needs a sample_period" in got[2][2]
    assert got[3][:2] == (5, 20) and "max_delay" in got[3][2]
    assert got[4][:2] == (6, 17) and "max_samples" in got[4][2]
    assert got[5][:2] == (7, 18) and "state policy field 'period'" in got[5][2]
    assert got[6][:2] == (8, 41) and "duplicate key 'change'" in got[6][2]
    assert got[7][:2] == (9, 14) and "needs a delta" in got[7][2]
    assert len(got) == 8
    assert errors("source a\nstate s = {x: a} every 1 missing maybe\n")[0][:2] == (2, 26)


def test_unknown_labels_and_known_instance_labels() -> None:
    text = "cu x = m:f inputs car/speed, car/pos output y\nstate s = {v: y, w: nope} every 1\n"
    got = errors(text)
    assert got == [
        (1, 19, "unknown label 'car/speed': no declaration provides it"),
        (1, 30, "unknown label 'car/pos': no declaration provides it"),
        (2, 21, "unknown label 'nope': no declaration provides it"),
    ]
    assert errors(text, known=("car/speed", "car/pos", "nope")) == []
    # a feature without a label in 'with' is read from the label of its own name
    assert (
        errors('monitor m = "always p" every 1')[0][2]
        == "unknown label 'p': no declaration provides it"
    )
    assert errors('source a\nchronicle c { input e = "x/{id}/a"\n event a = e }')[0][2] == (
        "no declared or existing label matches 'x/{id}/a'"
    )
    assert errors("source a", known=("a",)) == [(1, 1, "label 'a' exists already on the instance")]


def test_bad_formulas_are_positioned_in_the_file() -> None:
    text = 'source s\nmonitor m = "always[0,10] (s << 3)" every 1 with {s: s}\n'
    got = errors(text)
    # the quote is at column 13, the formula's second '<' is its column 18
    assert got == [(2, 31, "formula: expected a constant, found '<'")]
    assert errors('source s\nmonitor m = "s > 1" every 1 with {s: s, t: s}')[0] == (
        2, 41, "formula reads no feature 't'",
    )  # fmt: skip
    assert "period" in errors('source s\nmonitor m = "s > 1" every 0 with {s: s}')[0][2]


def test_duplicates_cycles_and_chronicle_errors() -> None:
    text = (
        "source a\n"
        "source a\n"
        "cu f = m:f inputs a output b\n"
        "cu f = m:f inputs a output c\n"
        "cu g = m:f inputs h output h\n"
        "chronicle k { input e = a\n event x = e\n event y = e\n constraint x -> y in [5, 1] }\n"
        "chronicle n { event x = e }\n"
    )
    got = errors(text)
    assert (2, 1, "label 'a' is declared twice (first at line 1)") in got
    assert (4, 1, "duplicate cu 'f' (first declared at line 3)") in got
    assert (5, 1, "cu 'g' depends on itself") in got
    assert any(e[:2] == (9, 13) and "lo 5.0 is greater than hi 1.0" in e[2] for e in got)
    # processes `m`, `monitor:m`, `chronicle:m` and their labels: no two alike
    same_name = (
        "source a\ncu m = mod:f inputs a output b\n"
        'monitor m = "always a > 1" every 1\n'
        "chronicle m { input k = a\n event e = k }\n"
    )
    assert errors(same_name) == []
    # at the event that needs the input, not at the chronicle
    assert (10, 21, "chronicle 'n': no 'input e = LABEL' for event 'e'") in got
    assert errors(
        "chronicle c {\n  input a = x\n  event s = a\n  forbidden b between s and s\n}"
    ) == [
        (2, 13, "unknown label 'x': no declaration provides it"),
        (4, 3, "chronicle 'c': no 'input b = LABEL' for event 'b'"),
    ]


# -- setup -------------------------------------------------------------------------------------

APP = """\
source car/speed
source car/offset
cu smooth = examples.kpl_functions:make_smoother(alpha=1.0)
    inputs car/speed with {lower: 0} output car/smooth
cu road = examples.kpl_functions:on_road inputs car/offset output car/on_road
stream car/sampled = car/smooth with {sample_period: 1, approximation: most_recent}
state car/state = {speed: car/smooth, on_road: car/on_road} every 1 latest
monitor slow = "always[0,2] (speed < 30 -> on_road)" every 1
    with {speed: car/smooth, on_road: car/on_road}
changes car/on_road
chronicle back_on_road {
    input on_road = events/changed/car/on_road
    event leave = on_road from true to false
    event back = on_road from false to true
    constraint leave -> back in [0, 5]
}
"""


def test_setup_flows_and_remove() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    app = setup(inst, APP)
    assert app.processes[:2] == ["source:car/speed", "source:car/offset"]
    assert len(app.processes) == 9 and app.unsupported == []
    got: dict[str, list[Any]] = {}
    for label in ("car/smooth", "car/sampled", "car/state", "monitors/slow"):
        got[label] = []
        inst.subscribe(label, callback=got[label].extend)
    got["chronicles/back_on_road"] = []
    inst.subscribe("chronicles/back_on_road", callback=got["chronicles/back_on_road"].extend)
    speed = inst.processes["source:car/speed"]
    offset = inst.processes["source:car/offset"]
    for k, (v, off) in enumerate([(10, 0), (40, 10), (10, 0), (10, 10), (10, 0)]):
        t = k * NS_PER_S
        speed.push(v, valid_time=t, available_time=t)  # type: ignore[attr-defined]
        offset.push(off, valid_time=t, available_time=t)  # type: ignore[attr-defined]
    speed.push(-5, valid_time=5 * NS_PER_S, available_time=5 * NS_PER_S)  # type: ignore[attr-defined]
    assert [v for v, _, _ in got["car/smooth"]] == [10, 40, 10, 10, 10]  # -5 is out of bounds
    assert [(v, tv // NS_PER_S) for v, tv, _ in got["car/sampled"]][:3] == [
        (10, 0), (40, 1), (10, 2),
    ]  # fmt: skip
    assert got["car/state"][0][0] == {"speed": 10, "on_road": True}
    verdicts = [(v["verdict"], tv // NS_PER_S) for v, tv, _ in got["monitors/slow"]]
    assert verdicts == [(True, 2), (False, 3)]
    assert len(got["chronicles/back_on_road"]) >= 1
    app.remove()
    assert app.processes == [] and inst.processes == {}
    assert not any(inst.has_label(x) for x in ("car/speed", "car/smooth", "monitors/slow"))


def test_setup_refuses_what_does_not_check_and_rolls_back_failures() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    inst.add_source("existing")
    with pytest.raises(KPLCheckError) as info:
        setup(inst, "stream a = existing with {upper: nan_value}\nstream b = nowhere")
    assert [(e.line, e.column) for e in info.value.errors] == [(1, 27), (2, 12)]
    assert set(inst.processes) == {"source:existing"}
    bad = "stream a = existing\ncu f = examples.kpl_functions:no_such_fn inputs a output b\n"
    with pytest.raises(KPLSetupError) as info2:
        setup(inst, bad)
    assert (info2.value.line, info2.value.column) == (2, 1)
    assert "no_such_fn" in str(info2.value)
    assert set(inst.processes) == {"source:existing"} and not inst.has_label("a")
    app = setup(inst, parse("stream a = existing with {sample_period: 1}"))
    assert app.processes == ["stream:a"]


# -- the command --------------------------------------------------------------------------------


def test_cli_check_in_process(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert dyknow_main(["kpl", "check", str(EXAMPLE)]) == 0
    assert capsys.readouterr().out.startswith("ok: ")
    bad = tmp_path / "bad.kpl"
    bad.write_text("source a\nstream b = c\n")
    assert dyknow_main(["kpl", "check", str(bad)]) == 2
    assert capsys.readouterr().err == f"{bad}:2:12: unknown label 'c': no declaration provides it\n"
    assert dyknow_main(["kpl", "check", str(tmp_path / "missing.kpl")]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_cli_check_subprocess(tmp_path: Path) -> None:
    exe = Path(sys.executable).parent / "dyknow"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "federation.cli"]
    ok = subprocess.run([*cmd, "kpl", "check", str(EXAMPLE)], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.strip() == f"ok: {len(parse(EXAMPLE.read_text()).decls)} declarations"
    bad = tmp_path / "bad.kpl"
    bad.write_text('source s\nmonitor m = "s <" every 1 with {s: s}\n')
    res = subprocess.run([*cmd, "kpl", "check", str(bad)], capture_output=True, text=True)
    assert res.returncode == 2
    assert res.stderr.splitlines() == [
        f"{bad}:2:17: formula: expected a constant, found end of formula"
    ]


def test_text_the_tokenizer_drops_is_reported_once_not_echoed_by_the_parser() -> None:
    # the string runs to the end of its line; what the declaration misses after it is
    # the same mistake: one error, and the next declarations are still checked
    assert errors('source "abc\nsource b\nstream c = b with {frob: 1}\n') == [
        (1, 8, "unterminated string"),
        (3, 20, "unknown policy field 'frob' (known: start, end, sample_period, approximation, "
         "max_delay, late, order, change, lower, upper, buffer_size, overflow)"),
    ]  # fmt: skip
    assert errors('source a\nstream b = a with {x: "abc}\nsource c\n') == [
        (2, 23, "unterminated string")
    ]
    assert errors("source a$b\nsource c\n") == [(1, 9, "unexpected character '$'")]
    # the declaration took the next line's word as the label the string was: not its error
    assert errors('source a\nstream b = "abc\n  with {x: 1}\nsource c\n') == [
        (2, 12, "unterminated string")
    ]
    # a stray character drops only itself: a later error of its declaration is its own
    assert errors("source a\ncu f = m:g$ inputs a output\n") == [
        (2, 11, "unexpected character '$'"),
        (3, 1, "expected the output label, found end of file"),
    ]
    assert errors("chronicle c {\n input k = a$\n event e = k\n constraint e -> 1\n}\n") == [
        (2, 13, "unexpected character '$'"),
        (4, 18, "expected an event name, found '1'"),
    ]
    # an error before the dropped text is still its own
    assert errors('stream = "abc\n') == [
        (1, 8, "expected a label, found '='"),
        (1, 10, "unterminated string"),
    ]


def test_a_label_with_a_dash_is_asked_to_be_quoted() -> None:
    # vocabularies spell labels `wind-speed`: a bare one is told how to write it
    hint = "must be quoted: a bare label is letters, digits, '_', '.' and '/'"
    assert errors("source wind-speed\nstate s = {w: heli-position} every 1\n") == [
        (1, 8, f"label 'wind-speed' {hint} (write \"wind-speed\")"),
        (2, 15, f"label 'heli-position' {hint} (write \"heli-position\")"),
    ]
    assert errors('source "wind-speed"\nstream w = "wind-speed"\n') == []


def test_cli_check_resolves_labels_only_once_the_file_parses(tmp_path: Path) -> None:
    # a declaration the syntax error dropped may provide the label: no noise about it yet
    exe = Path(sys.executable).parent / "dyknow"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "federation.cli"]
    bad = tmp_path / "typo.kpl"
    text = "source a\n{kw} b\nstream c = nowhere\nstream d = a with {{frob: 1}}\n"
    bad.write_text(text.format(kw="sorce"))
    res = subprocess.run(
        [*cmd, "kpl", "check", str(bad)], capture_output=True, text=True, timeout=60
    )
    assert res.returncode == 2
    assert [line.split(": ")[0] for line in res.stderr.splitlines()] == [
        f"{bad}:2:1",
        f"{bad}:4:20",
    ]
    assert "found 'sorce'" in res.stderr and "unknown policy field 'frob'" in res.stderr
    bad.write_text(text.format(kw="source"))
    res = subprocess.run(
        [*cmd, "kpl", "check", str(bad)], capture_output=True, text=True, timeout=60
    )
    assert res.returncode == 2
    assert res.stderr.splitlines()[0] == (
        f"{bad}:3:12: unknown label 'nowhere': no declaration provides it"
    )


# -- classes and links ---------------------------------------------------------------------------


def test_class_and_link_errors_have_positions() -> None:
    assert errors("class A { base B }") == [(1, 16, "base class 'B' is not declared")]
    assert errors("class B { base A }\nclass A { }") == [
        (1, 16, "base class 'A' must be declared before it")
    ]
    assert errors('class A {\n  feature x = "a/x"\n}') == [
        (2, 11, "class 'A': features.x: label pattern 'a/x' has no {id}")
    ]
    # the formula's error position, mapped into the file (column 1 just after the quote)
    assert errors('class A { base B\n  add "on_road &&" }') == [
        (1, 16, "base class 'B' is not declared"),
        (2, 16, "add: unexpected character '&'"),
    ]
    assert errors('class A { add "x" }') == [
        (1, 11, "class 'A': add: an add constraint needs a base class to draw candidates from")
    ]
    assert errors('class A { create "x" }') == [
        (1, 11, "class 'A': create_from: give both create and create_from, or neither")
    ]
    assert errors('class A { create "x" from nowhere }') == [
        (1, 27, "unknown label 'nowhere': no declaration provides it")
    ]
    assert errors("class A { base A }") == [
        (1, 11, "class 'A': base: a class cannot be its own base")
    ]
    assert errors("class A { prefix p prefix q }") == [(1, 20, "duplicate clause 'prefix'")]
    assert errors("class A { }\nclass A { }") == [
        (2, 1, "duplicate class 'A' (first declared at line 1)")
    ]
    got = errors("class A { frob x }")
    assert got[0][:2] == (1, 11) and "unknown class clause 'frob'" in got[0][2]
    assert errors("class A { }\nlink L { from A to A }") == [
        (2, 17, "link 'L': to_class: a link joins two different classes")
    ]
    assert errors("class A { }\nlink L { from A }") == [
        (2, 1, "link 'L': to_class: Field required")
    ]
    assert errors('class A { }\nlink L { from A to B\n establish "x <" }') == [
        (2, 20, "unknown class 'B'"),
        (3, 16, "establish: expected a constant, found end of formula"),
    ]
    assert errors("class A { }\nclass B { }\nlink L { from A to B }\nlink L { from B to A }") == [
        (4, 1, "duplicate link 'L' (first declared at line 3)")
    ]
    got = errors("class A { }\nlink L { via A }")
    assert got[0][:2] == (2, 10) and "unknown link clause 'via'" in got[0][2]
    assert errors("link L { from A to B }")[0] == (
        1, 1, "link 'L' needs at least one class declaration",
    )  # fmt: skip
    assert errors("class A { }\nanchoring every 0") == [
        (2, 17, "anchoring period: period must be between 1e-06 and 1e+09 s, got 0")
    ]
    assert errors("class A { }\nanchoring every 1\nanchoring every 2") == [
        (3, 1, "duplicate anchoring 'anchoring' (first declared at line 2)")
    ]
    assert errors("anchoring every 1") == [(1, 1, "anchoring needs at least one class declaration")]
    assert errors("class A { }", ("events/anchoring",))[0][:2] == (1, 1)
    assert errors("class A { }\nanchoring every 1 output x", ("x",)) == [
        (2, 1, "label 'x' exists already on the instance")
    ]


def test_class_functions_resolve_at_setup_only() -> None:
    text = "class A { relation r = examples.kpl_functions:no_such_fn }"
    assert check(text) == []  # not imported at check time
    inst = DyKnowInstance(clock=ManualClock())
    inst.add_source("existing")
    with pytest.raises(KPLSetupError) as info:
        setup(inst, "stream s = existing\n" + text)
    assert (info.value.line, info.value.column) == (2, 24) and "no_such_fn" in str(info.value)
    assert set(inst.processes) == {"source:existing"} and not inst.has_label("s")


ON_ROAD_APP = """\
source wo/wo1/on_road
class WorldObject {
    feature on_road = "wo/{id}/on_road"
}
class OnRoadObject {
    base WorldObject
    add "always[0,3] on_road"
    maintain "eventually[0,2] on_road"
}
anchoring every 1 output events/kpl_anchoring
"""


async def test_setup_anchoring_membership_follows_the_clock() -> None:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as inst:
        app = setup(inst, ON_ROAD_APP)
        assert app.processes == ["source:wo/wo1/on_road", "anchoring"] and app.unsupported == []
        anch = inst.processes["anchoring"]
        assert isinstance(anch, Anchoring)
        road = inst.processes["source:wo/wo1/on_road"]
        inst.objects.reserve("wo1")
        inst.objects.domain("WorldObject").add("wo1")

        async def settle(t: int) -> None:
            for _ in range(200):
                if anch.last_step is not None and anch.last_step >= t:
                    return
                await asyncio.sleep(0)
            raise AssertionError(f"anchoring did not step at {t}")

        async def step(on: bool) -> None:
            t = clock.now() + NS_PER_S
            road.push(on, valid_time=t)  # type: ignore[attr-defined]
            clock.set(t)
            await settle(t)

        road.push(True, valid_time=0)  # type: ignore[attr-defined]
        await settle(0)
        for _ in range(2):
            await step(True)
        assert "wo1" not in anch.members("OnRoadObject")  # on the road for 2 s only
        await step(True)
        assert "wo1" in anch.members("OnRoadObject")  # t = 3: on the road over [0, 3]
        for _ in range(3):
            await step(False)
        assert "wo1" not in anch.members("OnRoadObject")  # off over a whole 2 s window
        assert "wo1" in anch.members("WorldObject")
        kinds = [s.value["event"] for s in inst.between("events/kpl_anchoring", 0, 10**15).samples]
        assert kinds.count("joined") >= 1 and "left" in kinds
        app.remove()
        assert set(inst.processes) == set() and not inst.has_label("events/kpl_anchoring")


async def test_remove_takes_the_class_domains_it_created_and_their_labels() -> None:
    async with DyKnowInstance(clock=ManualClock()) as inst:
        inst.objects.add_domain("WorldObject", publish=True)  # the application's own
        app = setup(inst, ON_ROAD_APP)
        assert app.domains == ["OnRoadObject"] and inst.has_label("domain/OnRoadObject")
        app.remove()
        assert inst.objects.domains() == ["WorldObject"] and inst.labels() == ["domain/WorldObject"]
        setup(inst, ON_ROAD_APP).remove()  # set up again, as the first time
        assert inst.labels() == ["domain/WorldObject"]


async def test_remove_leaves_a_class_domain_a_running_anchoring_still_uses() -> None:
    # regression: app.remove() removed every class domain its anchoring had created, even
    # one that an anchoring set up since from Python still worked on
    async with DyKnowInstance(clock=ManualClock()) as inst:
        app = setup(inst, ON_ROAD_APP)
        assert sorted(app.domains) == ["OnRoadObject", "WorldObject"]
        mine = add_anchoring(
            inst, [ObjectClass(name="OnRoadObject")], name="mine", output="events/mine"
        )
        app.remove()
        assert inst.objects.domains() == ["OnRoadObject"]
        assert inst.has_label("domain/OnRoadObject") and inst.processes["mine"] is mine
        assert mine.running
