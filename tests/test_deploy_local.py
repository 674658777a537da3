"""deploy/local: the compose topology on loopback, started by `up`, stopped by `down`.

The one deployment it starts also shows the UAVs' application recognizing the seeded
world's violations (deploy/README.md, "The UAVs' application").
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import re
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from _load import slowdown

from agents.transports import free_tcp_port
from federation.cli import main as cli_main

ROOT = Path(__file__).resolve().parent.parent
LOCAL = ROOT / "deploy" / "local"
CLI = [sys.executable, "-m", "federation.cli"]
WORLD_SPEED = 3.0  # the seeded world's, its overtake ~11 s in instead of ~33 s


def _world_speed() -> float:
    """The world's speed for this run: at 3x each UAV's feed and application step 3x as
    often, which a process with a third of a CPU or less cannot keep up with: a loaded
    machine runs the world slower (1x at least)."""
    return WORLD_SPEED / min(WORLD_SPEED, slowdown())


def _env(run: Path, router: int, console: int) -> dict[str, str]:
    return {
        **os.environ,
        "PYTHON": sys.executable,
        "DYKNOW_LOCAL_RUN": str(run),
        "DYKNOW_LOCAL_ROUTER_PORT": str(router),
        "DYKNOW_LOCAL_CONSOLE_PORT": str(console),
        "DYKNOW_LOCAL_TIMEOUT": "120",
        "DYKNOW_LOCAL_WORLD_SPEED": str(_world_speed()),
        "XDG_RUNTIME_DIR": str(run.parent / "xdg"),
    }


def _script(name: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(LOCAL / name)], env=env, capture_output=True, text=True, timeout=180)


def _pids(run: Path) -> list[int]:
    log = (run / "honcho.log").read_text()
    return [int(p) for p in re.findall(r"started \(pid=(\d+)\)", log)]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _listening(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
    except OSError:
        return False
    return True


def _values(answer: dict[str, Any], label: str) -> list[Any]:
    result = answer.get(label)
    return [s[0] for s in result["samples"]] if isinstance(result, dict) else []


def _the_application_recognizes_the_seeded_world(
    dyknow: Callable[..., subprocess.CompletedProcess[str]], started: float
) -> None:
    """The UAVs' application (deploy/config/traffic-app.kpl) recognizes what the world did.

    Seed 7: in uav-a's area car9 drives over 1.2 x the limit from the start and car4
    overtakes car2 (the simulator's script ends it at t = 33.8 s of the world, which runs
    `WORLD_SPEED` x); in uav-c's, car6 turns in crossing c3 (t = 30.2 s). Asked as the
    operator with ``dyknow ask --from 0``, as deploy/README.md shows; run here, in the one
    world this module starts, as the wait for it (real time, over 10 s) is what a second
    deployment would cost.
    """
    labels = ("speeding", "violation", "true-violation")

    def until(uav: str, done: Callable[[dict[str, Any]], bool], within: float) -> dict[str, Any]:
        deadline = time.monotonic() + within
        answer: dict[str, Any] = {}
        while time.monotonic() < deadline:
            asked = dyknow("ask", *labels, "--platform", uav, "--from", "0")
            assert asked.returncode == 0, asked.stderr
            answer = json.loads(asked.stdout)
            if done(answer):
                return answer
            time.sleep(1.0)  # the world runs in real time: nothing here to await
        raise AssertionError(f"not within {within} s: {json.dumps(answer)[:2000]}")

    answer = until("uav-a", lambda a: bool(_values(a, "violation")), 90)
    assert time.monotonic() - started < 90
    assert _values(answer, "speeding")[0] == {"kind": "speeding", "cars": ["car9"]}
    # the first (the world repeats every 120 s of its own, 40 s at 3x: a later pass may be
    # in by the time asked)
    found = _values(answer, "violation")[0]
    assert (found["kind"], found["car"], found["other"]) == ("overtake", "car4", "car2")
    assert set(found) == {"kind", "car", "other", "start", "end", "x", "y"}
    # recognized from the camera's view, not copied: the truth has a label of its own,
    # and the recognition ends close to when and where the script ended it
    truth = until("uav-a", lambda a: bool(_values(a, "true-violation")), 30)
    ((true, true_valid, _),) = truth["true-violation"]["samples"]
    assert (true["kind"], true["car"], true["other"]) == ("overtake", "car4", "car2")
    assert abs(found["end"] - true_valid) < 5
    assert abs(found["x"] - true["x"]) < 80
    # what the console shows of a UAV, in the demo's shapes
    asked = dyknow("ask", "heli-position", "area", "tracked-cars", "--platform", "uav-a")
    assert asked.returncode == 0, asked.stderr
    now = json.loads(asked.stdout)
    (position,) = _values(now, "heli-position")
    assert set(position) == {"x", "y", "z"}
    (area,) = _values(now, "area")
    assert area["index"] == 0 and len(area["polygon"]) >= 4
    (cars,) = _values(now, "tracked-cars")
    assert {"id", "x", "y", "speed", "colour", "road"} <= set(cars["cars"][0])
    # the other chronicle, in the other UAV, by then
    answer = until("uav-c", lambda a: bool(_values(a, "violation")), 30)
    turn = _values(answer, "violation")[0]
    assert (turn["kind"], turn["car"], turn["other"]) == ("turn", "car6", None)
    assert turn["start"] < turn["end"]


@pytest.mark.timeout(400)
def test_up_ask_stream_down_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    (tmp_path / "xdg").mkdir(mode=0o700)
    router, console = free_tcp_port(), free_tcp_port()
    env = _env(run, router, console)
    monkeypatch.setenv("XDG_RUNTIME_DIR", env["XDG_RUNTIME_DIR"])  # the console's channel
    try:
        up = _script("up", env)
        assert up.returncode == 0, up.stdout + up.stderr
        started = time.monotonic()  # every platform ready: the world runs from here
        url = f"http://127.0.0.1:{console}/?token="
        assert f"the console: {url}" in up.stdout  # the URL with the console's token
        # the command it suggests is the README's, for a car uav-a sees (car1 it did not)
        assert "e.g. .venv/bin/dyknow ask car2-state -p uav-a --config" in up.stdout
        url = up.stdout.split("the console: ", 1)[1].split()[0]
        # every platform ready, keys made on first use, the configs on loopback
        assert (run / "config" / "keys" / "trust.json").exists()
        assert f"tcp/127.0.0.1:{router}" in (run / "config" / "uav-a.toml").read_text()
        with urllib.request.urlopen(url, timeout=10) as page:
            assert "operator console" in page.read().decode()
        # idempotent: a second up finds it running
        again = _script("up", env)
        assert again.returncode == 0 and "already up" in again.stdout, again.stderr
        operator = str(run / "config" / "operator.toml")

        def process(*args: str) -> subprocess.CompletedProcess[str]:
            """``dyknow ARGS`` as the operator, a process of its own, as a user runs it."""
            return subprocess.run(
                [*CLI, *args, "--config", operator, "--json", "--wait", "10"],
                env=env,
                capture_output=True,
                text=True,
                timeout=60,
            )

        def dyknow(*args: str) -> subprocess.CompletedProcess[str]:
            """The same in this process: the same code, without an interpreter's start
            (about half of a one-shot command's second)."""
            argv = [*args, "--config", operator, "--json", "--wait", "10"]
            code = cli_main(argv)
            out = capsys.readouterr()
            return subprocess.CompletedProcess(["dyknow", *argv], code, out.out, out.err)

        # uav-a's application, fed by the traffic world: cars appear as it sees them
        cars: list[str] = []
        for _ in range(30):
            done = process("labels", "--platform", "uav-a")
            assert done.returncode == 0, done.stderr
            labels = json.loads(done.stdout)["labels"]
            cars = [x for x in labels if re.fullmatch(r"car\d+-state", x)]
            if cars:
                break
        assert cars, labels
        done = dyknow("ask", cars[0], "--platform", "uav-a")
        assert done.returncode == 0, done.stderr
        [(state, valid, available)] = json.loads(done.stdout)[cars[0]]["samples"]
        assert {"x", "y", "vx", "vy", "speed", "colour", "road"} <= set(state)
        assert valid <= available
        # a stream while the console runs as the operator: it goes through the console
        done = dyknow("stream", "heli-position", "--platform", "uav-a", "--count", "3")
        assert done.returncode == 0, done.stderr
        rows = [json.loads(line) for line in done.stdout.splitlines()]
        assert len(rows) == 3 and all(len(r["value"]) == 3 for r in rows)
        # each UAV's top speed, as the demo's UAVs give it (what a leader weighs)
        done = dyknow("ask", "heli-max-speed", "--platform", "uav-b")
        assert done.returncode == 0, done.stderr
        [(top, _, _)] = json.loads(done.stdout)["heli-max-speed"]["samples"]
        assert top == 20.0
        # the console draws what the UAVs' applications see and recognize: positions,
        # areas, cars, and the overtake uav-a recognizes about 33 s into the world
        # (11 s at 3x)
        token = url.split("token=", 1)[1]
        state: dict[str, Any] = {}
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            request = urllib.request.Request(
                url.split("/?", 1)[0] + "/api/state", headers={"Authorization": f"Bearer {token}"}
            )
            with urllib.request.urlopen(request, timeout=10) as answer:
                state = json.loads(answer.read())
            uav_a = next((p for p in state["platforms"] if p["name"] == "uav-a"), {})
            overtakes = [
                v
                for v in state["violations"]
                if (v["kind"], v["reported-by"]) == ("overtake", "uav-a")
            ]
            if uav_a.get("position") and uav_a.get("area") and uav_a.get("cars") and overtakes:
                break
            time.sleep(1.0)  # the world runs in real time: nothing here to await
        assert uav_a["area"]["index"] == 0 and set(uav_a["position"]) == {"x", "y", "z"}, state
        assert {c["id"] for c in uav_a["cars"]} >= {"car2", "car4"}, state  # the overtakers
        assert [(v["car"], v["other"]) for v in overtakes] == [("car4", "car2")], state
        _the_application_recognizes_the_seeded_world(dyknow, started)
        pids = _pids(run)
        assert len(pids) == 5 and all(_alive(p) for p in pids)
    finally:
        down = _script("down", env)
    assert down.returncode == 0 and "deploy/local: down" in down.stdout, down.stderr
    # nothing left: no process honcho started, no port, the console's "stopped" line
    assert not any(_alive(p) for p in pids)
    assert not _listening(router) and not _listening(console)
    served = re.search(
        r"dyknow console: local channel: (\d+) commands", (run / "honcho.log").read_text()
    )
    assert served and int(served.group(1)) >= 3  # labels, ask, stream: through the console
    # every label the shipped configs map is one the deployment provides
    log = (run / "honcho.log").read_text()
    assert "here yet" not in log and "can match no stream" not in log
    again = _script("down", env)
    assert again.returncode == 0 and "nothing running" in again.stdout


@pytest.mark.timeout(300)
def test_up_fails_loudly_naming_the_service(tmp_path: Path) -> None:
    run = tmp_path / "run"
    (tmp_path / "xdg").mkdir(mode=0o700)
    router, console = free_tcp_port(), free_tcp_port()
    env = _env(run, router, console)
    with socket.socket() as taken:  # the console's port is taken: the operator cannot start
        taken.bind(("127.0.0.1", console))
        taken.listen()
        up = _script("up", env)
    assert up.returncode == 1, up.stdout
    assert "deploy/local: up failed: operator stopped" in up.stderr
    assert "operator | " in up.stderr  # its last lines, with the reason
    pids = _pids(run)
    assert pids and not any(_alive(p) for p in pids)  # everything it started is stopped
    assert not (run / "honcho.pid").exists()


def test_a_world_speed_reaches_each_feed_and_the_applications_windows(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    spec = importlib.util.spec_from_file_location("deploy_local", LOCAL / "local.py")
    assert spec is not None and spec.loader is not None
    local = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(local)
    config = local._configs(tmp_path, 7447, 2.0)
    for uav in ("uav-a", "uav-b", "uav-c"):
        text = (config / f"{uav}.toml").read_text()
        assert f'args = {{uav = "{uav}", seed = 7, speed = 2.0, period = 0.1}}' in text
    app = (config / "traffic-app.kpl").read_text()
    assert 'always[0, 1] fast(c))" every 0.1' in app and "max_delay 0.25" in app
    assert "in [0, 7.5]" in app and "in [0, 15]" in app and "anchoring every 0.5" in app
    same = local._configs(tmp_path / "1x", 7447)  # 1x: deploy/config's as they are
    assert (same / "traffic-app.kpl").read_text() == (
        ROOT / "deploy/config/traffic-app.kpl"
    ).read_text()
    for bad in ("0", "-1", "fast", "nan"):
        monkeypatch.setenv("DYKNOW_LOCAL_WORLD_SPEED", bad)
        with pytest.raises(SystemExit, match="DYKNOW_LOCAL_WORLD_SPEED"):
            local._world_speed()


async def test_the_world_feed_refuses_a_speed_that_is_none() -> None:
    from federation.demo._feed import world_feed

    for bad in (0, -2.0, math.inf, True):
        with pytest.raises(ValueError, match="speed"):
            await anext(world_feed("uav-a", speed=bad))
