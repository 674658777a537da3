"""The deployed UAV application (deploy/config/traffic-app.kpl) recognizes the seeded world's
violations from its camera feed, as ``dyknow demo traffic`` does: asked from another process."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from agents.keys import gen_keys, trust_keys
from agents.transports import free_tcp_port
from dyknow_core import NS_PER_S
from dyknow_core.kpl import ChronicleDecl, MonitorDecl, check, parse
from dyknow_core.reasoning.chronicles import Recognition
from federation.demo._traffic import CHRONICLES, SPEEDING
from federation.demo._units import crossings, relations, speeding, violations
from federation.demo._world import World

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "deploy" / "config"
CLI = [sys.executable, "-m", "federation.cli"]
ASK = ["--config", "operator.toml", "--json", "--wait", "10"]


class Deployment:
    """deploy/config on loopback: a router, UAV nodes, and the operator's one-shot commands."""

    def __init__(self, tmp: Path) -> None:
        self.dir = tmp / "config"
        self.dir.mkdir()
        self.router = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.federation = f"traffic-{uuid.uuid4().hex[:8]}"  # one of its own per test
        for f in [*CONFIG.glob("*.toml"), *CONFIG.glob("*.kpl")]:
            text = f.read_text().replace('"tcp/172.28.0.10:7447"', f'"{self.router}"')
            text = text.replace('federation = "traffic"', f'federation = "{self.federation}"')
            (self.dir / f.name).write_text(text)
        keys = self.dir / "keys"
        pubs = [gen_keys(name, keys)[2] for name in ("uav-a", "uav-c", "operator")]
        trust_keys(keys / "trust.json", pubs, federation=self.federation)
        runtime = tmp / "run"
        runtime.mkdir(mode=0o700)  # the local channels of this test's nodes
        self.env = {**os.environ, "PYTHONUNBUFFERED": "1", "XDG_RUNTIME_DIR": str(runtime)}
        self.procs: list[subprocess.Popen[str]] = []

    def spawn(self, *args: str) -> subprocess.Popen[str]:
        """A long-running ``dyknow`` command in the config directory."""
        proc = subprocess.Popen(
            [*CLI, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=self.dir,
            env=self.env,
        )
        self.procs.append(proc)
        return proc

    def start(self, *uavs: str) -> None:
        """The router, then each UAV's node, ready."""
        router = self.spawn("router", "--listen", self.router)
        assert router.stdout is not None
        listening = router.stdout.readline()  # the nodes connect to it: it listens first
        assert "listening on" in listening, listening + self.stop()
        nodes = {uav: self.spawn("node", "--config", f"{uav}.toml") for uav in uavs}
        for uav, node in nodes.items():
            assert node.stdout is not None
            ready = node.stdout.readline()  # bounded by the test's timeout
            assert f"{uav} ready" in ready, ready + self.stop()

    def ask(self, uav: str, *labels: str, history: bool = True) -> dict[str, Any]:
        """``dyknow ask LABELS --platform UAV [--from 0] --json`` as the operator."""
        done = subprocess.run(
            [*CLI, "ask", *labels, "--platform", uav, *(["--from", "0"] if history else []), *ASK],
            capture_output=True,
            text=True,
            cwd=self.dir,
            env=self.env,
            timeout=60,
        )
        assert done.returncode == 0, done.stderr
        answer: dict[str, Any] = json.loads(done.stdout)
        return answer

    def until(
        self,
        uav: str,
        labels: tuple[str, ...],
        done: Callable[[dict[str, Any]], bool],
        within: float,
    ) -> dict[str, Any]:
        """Ask until the answer satisfies ``done``, for at most ``within`` seconds."""
        deadline = time.monotonic() + within
        answer: dict[str, Any] = {}
        while time.monotonic() < deadline:
            answer = self.ask(uav, *labels)
            if done(answer):
                return answer
            time.sleep(2.0)  # the world runs in real time: nothing here to await
        raise AssertionError(f"not within {within} s: {json.dumps(answer)[:2000]}")

    def stop(self) -> str:
        """SIGINT every process, newest first; their stderr."""
        errs = []
        for proc in reversed(self.procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
            try:
                _, err = proc.communicate(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                _, err = proc.communicate(timeout=5)
            errs.append(err)
        self.procs.clear()
        return "\n".join(errs)


@pytest.fixture
def deployment(tmp_path: Path) -> Iterator[Deployment]:
    d = Deployment(tmp_path)
    try:
        yield d
    finally:
        d.stop()


def _values(answer: dict[str, Any], label: str) -> list[Any]:
    result = answer.get(label)
    return [s[0] for s in result["samples"]] if isinstance(result, dict) else []


@pytest.mark.timeout(300)
def test_the_uavs_recognize_the_speeding_the_overtake_and_the_turn_of_the_seeded_world(
    deployment: Deployment,
) -> None:
    # seed 7: in uav-a's area car9 drives over 1.2 x the limit from the start and car4
    # overtakes car2 (the simulator's script ends it at t = 33.8 s); in uav-c's, car6
    # turns in crossing c3 (t = 30.2 s)
    deployment.start("uav-a", "uav-c")
    started = time.monotonic()
    labels = ("speeding", "violation", "true-violation")
    answer = deployment.until("uav-a", labels, lambda a: bool(_values(a, "speeding")), 60)
    assert _values(answer, "speeding")[0] == {"kind": "speeding", "cars": ["car9"]}
    answer = deployment.until("uav-a", labels, lambda a: bool(_values(a, "violation")), 90)
    assert time.monotonic() - started < 90
    (found,) = _values(answer, "violation")
    assert (found["kind"], found["car"], found["other"]) == ("overtake", "car4", "car2")
    assert set(found) == {"kind", "car", "other", "start", "end", "x", "y"}
    # recognized from the camera's view, not copied: the truth has a label of its own,
    # and the recognition ends close to when and where the script ended it
    truth = deployment.until("uav-a", labels, lambda a: bool(_values(a, "true-violation")), 30)
    ((true, true_valid, _),) = truth["true-violation"]["samples"]
    assert (true["kind"], true["car"], true["other"]) == ("overtake", "car4", "car2")
    assert abs(found["end"] - true_valid) < 5
    assert abs(found["x"] - true["x"]) < 80
    # what the console shows of a UAV, in the demo's shapes
    now = deployment.ask("uav-a", "heli-position", "area", "tracked-cars", history=False)
    (position,) = _values(now, "heli-position")
    assert set(position) == {"x", "y", "z"}
    (area,) = _values(now, "area")
    assert area["index"] == 0 and len(area["polygon"]) >= 4
    (cars,) = _values(now, "tracked-cars")
    assert {"id", "x", "y", "speed", "colour", "road"} <= set(cars["cars"][0])
    # the other chronicle, in the other UAV, by then
    answer = deployment.until("uav-c", labels, lambda a: bool(_values(a, "violation")), 30)
    (turn,) = _values(answer, "violation")
    assert (turn["kind"], turn["car"], turn["other"]) == ("turn", "car6", None)
    assert turn["start"] < turn["end"]


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
