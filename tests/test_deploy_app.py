"""The deployed UAV application (deploy/config/traffic-app.kpl): its definitions and units.

That it recognizes the seeded world's violations from its camera feed, as ``dyknow demo
traffic`` does, asked from another process, is checked in tests/test_deploy_local.py, in
the deployment that test starts: the world runs in real time, and one run of it serves
both (over 30 s each).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from dyknow_core import NS_PER_S
from dyknow_core.kpl import ChronicleDecl, MonitorDecl, check, parse
from dyknow_core.reasoning.chronicles import Recognition
from federation.demo._traffic import CHRONICLES, SPEEDING
from federation.demo._units import crossings, relations, speeding, violations
from federation.demo._world import World

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "deploy" / "config"


# -- the application's definitions and units, without processes -------------------------------


def test_the_kpl_file_holds_the_demos_chronicles_and_monitor() -> None:
    text = (CONFIG / "traffic-app.kpl").read_text()
    assert check(text) == []
    decls = parse(text).decls
    chronicles = {
        d.name.replace("_", "-"): (d.spec(), {k: r.label for k, r in d.inputs.items()})
        for d in decls
        if isinstance(d, ChronicleDecl)
    }
    for name, (spec, inputs) in CHRONICLES.items():
        kpl_spec, kpl_inputs = chronicles.pop(name)
        assert {k: v for k, v in kpl_spec.items() if k not in ("name", "forbidden")} == {
            k: v for k, v in spec.items() if k != "name"
        }
        assert kpl_inputs == inputs
    assert chronicles == {}
    (monitor,) = [d for d in decls if isinstance(d, MonitorDecl)]
    assert monitor.formula == SPEEDING


def _car(x: float, y: float, vx: float = 10.0, road: str | None = "r1") -> dict[str, Any]:
    return {"x": x, "y": y, "vx": vx, "vy": 0.0, "speed": abs(vx), "colour": "red", "road": road}


def test_a_relation_unit_reports_pairs_that_change_at_once_one_sample_each() -> None:
    behind = relations("behind")
    # three pairs come into "behind" at the same instant (car1 behind car0, car2 behind
    # both): all are reported, one per camera sample
    cars = {"car0": _car(100, 198), "car1": _car(80, 198), "car2": _car(70, 198)}
    assert behind(cars) == {"a": "car1", "b": "car0"}
    assert behind(cars) == {"a": "car2", "b": "car0"}
    assert behind(cars) == {"a": "car2", "b": "car1"}
    assert behind(cars) is None  # still behind: no change, nothing new
    with pytest.raises(ValueError, match="kind 'aside'"):
        relations("aside")
    with pytest.raises(TypeError, match="camera/cars"):
        behind([1, 2])


def test_a_crossing_unit_reports_a_turn_after_the_entry() -> None:
    world = World.generate(7, 3, 120.0)
    c = world.crossings[0]
    enter, turn = crossings("enter"), crossings("turn")
    road_in = world.road_at(c.x - c.radius - 3, c.y)
    assert road_in is not None  # an east-west road goes through the crossing
    outside = _car(c.x - c.radius - 3, c.y, road=road_in)
    inside = _car(c.x, c.y, road=None)
    away = _car(c.x, c.y + c.radius + 3, road="elsewhere")
    assert enter({"car1": outside}) is None and turn({"car1": outside}) is None
    assert enter({"car1": inside}) == {"car": "car1", "crossing": c.id}
    assert turn({"car1": inside}) is None
    assert turn({"car1": away}) == {"car": "car1", "crossing": c.id}


def test_the_speeding_unit_reports_a_new_violation_verdict_once_per_car() -> None:
    unit = speeding()
    violated = {"verdict": False, "formula": SPEEDING, "start": 0}
    assert unit(violated, {"car9": True, "car2": False}) == {"kind": "speeding", "cars": ["car9"]}
    assert unit(violated, {"car9": True, "car3": True}) is None  # a new `fast`, same verdict
    again = dict(violated)
    assert unit(again, {"car9": True, "car3": True}) == {"kind": "speeding", "cars": ["car3"]}
    assert unit(again, {"car9": False, "car3": True}) is None
    later = dict(violated)  # car9 slowed down, then sped again: a new violation
    assert unit(later, {"car9": True, "car3": True}) == {"kind": "speeding", "cars": ["car9"]}
    assert unit({"verdict": True}, {"car9": True}) is None


def test_the_violations_unit_reports_each_recognition_once_reckless_first() -> None:
    unit = violations()
    s = NS_PER_S
    times = {"behind": 10 * s, "beside": 14 * s, "ahead": 18 * s}
    overtake = Recognition("overtake", {"a": "car4", "b": "car2"}, times)
    reckless = Recognition("reckless_overtake", {"a": "car4", "b": "car2"}, times)
    cars = {"car4": _car(385.0, 198.0)}
    state = {"cars": cars, "overtake": overtake, "reckless_overtake": reckless, "turn": None}
    assert unit(state) == {
        "kind": "reckless-overtake",
        "car": "car4",
        "other": "car2",
        "start": 14.0,
        "end": 18.0,
        "x": 385.0,
        "y": 198.0,
    }
    assert unit(state) is None  # the same recognitions in the next state: nothing new
    turn = Recognition("turn", {"car": "car6", "crossing": "c3"}, {"enter": 26 * s, "turn": 30 * s})
    assert unit({**state, "turn": turn}) == {
        "kind": "turn",
        "car": "car6",
        "other": None,
        "start": 26.0,
        "end": 30.0,
        "x": None,
        "y": None,
    }
