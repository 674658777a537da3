"""The examples run as the README says, and show what they claim to show."""

import json
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from _node_example import Station, _samples, _stats

from dyknow_core import NS_PER_S
from examples import (
    anchoring,
    chronicle,
    cu,
    federation_query,
    local_pipeline,
    monitor,
    policy,
    state,
    stream_between_platforms,
)

ROOT = Path(__file__).resolve().parent.parent


async def test_local_pipeline_demo_runs_and_fills_the_gps_tunnel(capsys) -> None:  # type: ignore[no-untyped-def]
    metrics = await local_pipeline.run(pace=0)
    out = capsys.readouterr().out
    # one odometer reading per simulated second, tunnel included: the periodic policy's
    # late='approximate' filled the seconds the GPS was silent
    assert metrics["car5/odometer"]["samples_in"] == int(local_pipeline.DRIVE_S)
    # glitches (out of bounds) and stale readings (over max delay) never reach the smoother
    assert metrics["car5/speed"]["dropped"] > 0
    assert metrics["car5/speed_smooth"]["samples_in"] < metrics["car5/speed"]["samples_in"]
    assert "speeding" in out
    assert "process failures: 0" in out


async def test_two_platforms_example_answers_through_the_interface_agents(capsys) -> None:  # type: ignore[no-untyped-def]
    from examples import two_platforms

    result = await two_platforms.run()
    assert result["answer"] == {"asked": {"where": "area X"}, "wind_m_s": 4.2}
    # the request was authenticated and access-checked on uav-a before the agent saw it
    assert result["audit"]["accepted"] >= 1
    assert result["audit"]["dropped"] == 0
    assert "wind" in capsys.readouterr().out


# -- one capability per script: examples/<name>.py ------------------------------------------


@pytest.mark.parametrize(
    "script",
    [
        "policy.py",
        "cu.py",
        "state.py",
        "monitor.py",
        "chronicle.py",
        "anchoring.py",
        "federation_query.py",
        "stream_between_platforms.py",
        "local_pipeline.py --fast",
        "two_platforms.py",
    ],
)
def test_each_example_runs_as_a_script(script: str) -> None:
    # as examples/README.md says: python examples/<name>.py, from anywhere
    name, *args = script.split()
    done = subprocess.run(
        [sys.executable, str(ROOT / "examples" / name), *args],
        capture_output=True,
        text=True,
        timeout=50,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() and "Traceback" not in done.stderr


async def test_policy_example_drops_late_and_out_of_order_and_fills_the_silence() -> None:
    result = await policy.run()
    assert result["published"] == 18
    grid = [(valid // NS_PER_S, value) for value, valid, _ in result["display"]]
    assert grid == [(0, 20.0), (1, 21.0), (2, 22.0), (3, 22.25), (4, 24.25), (5, 25.0), (6, 26.0)]
    # 3 s: nothing came within the max delay; decided by time, at 3.5 s, from 2.25 s
    assert result["display"][3][2] == int(3.5 * NS_PER_S)
    stats = result["stats"]
    assert (stats["dropped_late"], stats["dropped_order"], stats["approximated"]) == (2, 1, 1)


async def test_cu_example_computes_filters_and_survives_a_failure() -> None:
    result = await cu.run()
    # the error code -1 at 3 s never reaches the unit: its input policy's bounds
    assert result["wx/wind_kmh"] == [(18.0, 0), (18.0, 1), (21.6, 2), (36.0, 4)]
    # too warm at 1 s: None, nothing emitted; 2 s: raised twice; both inputs fire it at 4 s
    assert [t for _, t in result["wx/wind_chill"]] == [0, 3, 4, 4]
    assert result["wx/wind_chill"][0] == (1.3, 0)
    assert result["failures"] == ["chill", "chill"]


async def test_state_example_synchronizes_waits_and_skips() -> None:
    result = await state.run()
    valid = [tv for _, tv, _ in result["states"]]
    assert valid == [1.0 + 0.5 * k for k in range(9)]  # before 1 s: no on-road flag, skipped
    assert result["skipped"] == 2 and result["emitted"] == 9
    lost = [(v["pos"], ta - tv) for v, tv, ta in result["states"] if 2.0 <= tv <= 3.0]
    # the GPS is lost: each waits its max delay, then takes the position of 1.5 s
    assert [p for p, _ in lost] == [(16.6, 0.0)] * 3
    assert all(abs(wait - 0.4) < 1e-9 for _, wait in lost)


async def test_monitor_example_reports_the_violation_when_it_is_certain() -> None:
    assert await monitor.run() == [(True, 10, 0), (True, 21, 11), (False, 33, 22)]


async def test_chronicle_example_recognizes_each_pass_per_car() -> None:
    # car2 stayed 25 s in the crossing: over the 20 s constraint, never recognized
    assert await chronicle.run() == [("car1", 2, 8), ("car3", 10, 14), ("car3", 41, 50)]


async def test_anchoring_example_joins_and_leaves_on_road() -> None:
    events = await anchoring.run()
    assert (0, "linked", "vo2wo", "visionobject1 -> worldobject1") in events
    on_road = [(t, e) for t, e, cls, _ in events if cls == "OnRoadObject"]
    assert on_road == [(10, "joined"), (35, "left")]
    # b2's faint blob never became an object
    assert [who for _, e, _, who in events if e == "created"] == ["visionobject1", "worldobject1"]
    # each object is reported created before it joins its class, a percept or a link's end
    created_then_joined = [(e, who) for t, e, _, who in events if t == 0 and "->" not in who]
    assert created_then_joined == [
        ("created", "visionobject1"),
        ("joined", "visionobject1"),
        ("created", "worldobject1"),
        ("joined", "worldobject1"),
    ]


@pytest.mark.timeout(30)
async def test_federation_query_example_asks_every_platform() -> None:
    result = await federation_query.run()
    assert result["altitude"] == {"uav-a": 120.0, "uav-b": 85.5}
    assert result["newest"] == "uav-b"
    assert result["car5"] == ["uav-a"]
    assert list(result["refused"]) == ["uav-b"] and "no stream" in result["refused"]["uav-b"]


@pytest.mark.timeout(30)
async def test_stream_between_platforms_example_exports_with_the_policy() -> None:
    got = await stream_between_platforms.run()
    assert [valid for _, valid in got] == [2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    # the states of 4.8 s to 5.2 s were late at uav-a: 5 s took the state of 4.7 s
    assert [state["x"] for state, _ in got] == [25.0, 37.5, 50.0, 58.75, 75.0, 87.5, 100.0]


# -- examples/node: a node running weather.kpl, fed by each kind of input ----------------------


@pytest.fixture
def station(tmp_path: Path) -> Iterator[Station]:
    s = Station(tmp_path)
    try:
        yield s
    finally:
        s.stop()


@pytest.mark.timeout(90)
def test_node_example_file_inputs_replay_jsonl_and_csv(station: Station) -> None:
    station.start("file")
    # the JSON-lines file at its recorded pace (2 s), shifted to now; the CSV at once
    answer = station.latest(
        "temperature", "wind-speed-kmh", until=lambda a: _samples(a, "temperature")[0][0] == 19.5
    )
    assert _samples(answer, "wind-speed-kmh")[0][0] == 46.8  # 13 m/s through the KPL's CU
    history = station.dyknow("ask", "temperature", "-p", "station", "--from", "0")
    values = [s[0] for s in _samples(history, "temperature")]
    assert sorted(v for v in values if v < 15) == [10, 11, 12, 13, 14]  # the CSV rows
    # the CSV kept its recorded valid times (60 s before the JSON lines' first)
    csv_valid = sorted(s[1] for s in _samples(history, "temperature") if s[0] < 15)
    assert csv_valid == [1763999940.0, 1763999950.0, 1763999960.0, 1763999970.0, 1763999980.0]
    out, err = station.stop()
    stats = {row.get("input"): row for row in _stats(out)}
    jsonl = next(v for k, v in stats.items() if k and k.endswith("observations.jsonl"))
    assert jsonl["received"] == 11 and jsonl["samples"] == 20
    assert jsonl["bad"] == {"bad-time": 1}  # the "yesterday" line: counted and logged
    assert "bad-time" in err and "'yesterday' is not a number" in err and "Traceback" not in err


@pytest.mark.timeout(90)
def test_node_example_python_input(station: Station) -> None:
    station.start("python")
    answer = station.latest("temperature", "weather", until=lambda a: bool(_samples(a, "weather")))
    [(value, valid, available)] = _samples(answer, "temperature")
    assert 19.0 <= value <= 21.0 and valid <= available
    state = _samples(answer, "weather")[0][0]
    assert set(state) == {"temperature", "wind"} and state["wind"] >= 3.0 * 3.6
    rows = station.dyknow("stream", "wind-speed-kmh", "-p", "station", "--count", "2")
    assert len(rows) == 2 and all(r["label"] == "wind-speed-kmh" for r in rows)
    # docs/application.md: `ask --json` in seconds, `stream --json` in integer ns
    assert isinstance(valid, float) and 1.7e9 < valid < 1e10
    assert all(isinstance(r["valid"], int) and r["valid"] > 1.7e18 for r in rows)
    assert abs(rows[0]["valid"] / NS_PER_S - valid) < 60


@pytest.mark.timeout(90)
def test_a_stream_with_no_reading_gives_up_after_its_timeout_saying_so(station: Station) -> None:
    # docs/application.md: `stream` gives up after --timeout when no reading comes; the
    # zenoh station has no publisher here, so none does
    station.start("zenoh")
    # the stream's request (a key exchange first) waits for its answer up to --timeout too:
    # 5 s leave a loaded machine room for it, so that the error is the one of no reading
    stream = station.spawn(
        *("stream", "temperature", "-p", "station", "--count", "3"),
        *("--timeout", "5", "--config", "operator.toml"),
    )
    out, err = stream.communicate(timeout=60)
    assert stream.returncode == 1 and out == "", (out, err)
    # in words, as a refusal or a silent platform is (the class is for unexpected errors)
    assert err == "dyknow: no sample of 'temperature' from station arrived within 5.0 s\n"
    # the station's own stream, through its node's local channel: bounded the same way
    own = station.command(
        *("stream", "temperature", "-p", "station", "--count", "3"),
        *("--timeout", "3", "--config", "station-zenoh.toml"),
        timeout=60,
    )
    assert own.returncode == 1 and own.stdout == "", own
    assert own.stderr == "dyknow: no sample of 'temperature' from station arrived within 3.0 s\n"


READINGS = 20  # put by publish_zenoh.py, 0.1 s apart


@pytest.mark.timeout(90)
def test_node_example_zenoh_input_and_output(station: Station) -> None:
    station.start("zenoh")
    endpoint = f"tcp/127.0.0.1:{station.port}"
    # a plain zenoh subscriber (not our library) reads the state the node puts out
    listener = subprocess.Popen(
        [sys.executable, "-c", ZENOH_LISTENER, endpoint, "dyknow/station/**"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=station.env,
    )
    try:
        # the node puts its state out as inputs arrive: subscribe before anything is sent
        assert listener.stdout is not None
        ready = _readline(listener.stdout, 30.0)
        assert ready.strip() == "ready", listener.stderr.read() if listener.stderr else ready
        # 20 readings 0.1 s apart span over 1 s of valid time, so they pass at least one
        # point of the state's 1 s grid: a state is decided only when its inputs pass one
        # (10 readings, 0.9 s, fell within one second about one run in ten: no state)
        publish = subprocess.run(
            [sys.executable, "publish_zenoh.py", endpoint, str(READINGS)],
            cwd=station.dir,
            env=station.env,
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert publish.returncode == 0, publish.stderr
        answer = station.latest(
            "temperature",
            "wind-speed",
            until=lambda a: _samples(a, "temperature")[0][0] == 18.0 + READINGS - 1,
        )
        assert _samples(answer, "wind-speed")[0][0] == 2.0 + READINGS - 1
        out, _ = listener.communicate(timeout=30)
    finally:
        if listener.poll() is None:
            listener.kill()
    key, payload = out.splitlines()[0].split(" ", 1)
    assert key == "dyknow/station/wx/state"
    sample = json.loads(payload)
    assert sample["label"] == "wx/state" and set(sample["value"]) == {"temperature", "wind"}
    out, _ = station.stop()
    [zin] = [r for r in _stats(out) if r.get("input") == "zenoh weather/*"]
    assert zin["received"] == READINGS + 1 and zin["samples"] == 2 * READINGS
    assert zin["bad"] == {"not-json": 1}


def _readline(stream: Any, timeout: float) -> str:
    """One line of a child's output, or "" when none came within ``timeout`` s."""
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.append(stream.readline()), daemon=True)
    reader.start()
    reader.join(timeout)
    return lines[0] if lines else ""


ZENOH_LISTENER = """
import json, sys, zenoh
c = zenoh.Config()
c.insert_json5("mode", '"client"')
c.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
c.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(c) as s, s.declare_subscriber(sys.argv[2]) as sub:
    print("ready", flush=True)
    sample = sub.recv()
    print(sample.key_expr, sample.payload.to_bytes().decode(), flush=True)
"""


@pytest.mark.timeout(90)
def test_node_example_mqtt_input_from_mosquitto_pub(
    tmp_path: Path, mosquitto: tuple[str, int]
) -> None:
    host, port = mosquitto
    station = Station(tmp_path, mqtt_port=port)
    pub = shutil.which("mosquitto_pub")
    sub = shutil.which("mosquitto_sub")
    assert pub and sub, "mosquitto-clients is needed (make mosquitto installs it)"
    try:
        station.start("mqtt")
        # the node's output, read by a real MQTT client
        listener = subprocess.Popen(
            [sub, "-h", host, "-p", str(port), "-t", "dyknow/station/#", "-C", "1", "-v"],
            stdout=subprocess.PIPE,
            text=True,
        )
        time.sleep(0.5)  # mosquitto_sub gives no sign that it subscribed
        t = 1764000000.25
        for message in (
            json.dumps({"time": t, "temperature": 21.5, "wind": 3.2}),
            "{not json",
            json.dumps({"humidity": 40}),
        ):
            subprocess.run(
                [pub, "-h", host, "-p", str(port), "-t", "weather/station1", "-m", message],
                check=True,
                timeout=10,
            )
        answer = station.latest(
            "temperature", "wind-speed-kmh", until=lambda a: bool(_samples(a, "wind-speed-kmh"))
        )
        assert _samples(answer, "temperature")[0][:2] == [21.5, t]  # the message's own time
        assert _samples(answer, "wind-speed-kmh")[0][:2] == [11.52, t]
        out, _ = listener.communicate(timeout=20)
        topic, payload = out.strip().split(" ", 1)
        assert topic == "dyknow/station/wx/wind_kmh"
        assert json.loads(payload)["value"] == 11.52 and json.loads(payload)["valid"] == t
        out, err = station.stop()
        [row] = [r for r in _stats(out) if r.get("input") == "mqtt weather/+"]
        assert row["received"] == 3 and row["samples"] == 2
        assert row["bad"] == {"not-json": 1, "no-field": 1}
        assert "none of the fields temperature, wind" in err
    finally:
        station.stop()


@pytest.mark.timeout(90)
def test_node_example_ros2_topics_published_as_rmw_zenoh_does(station: Station) -> None:
    station.start("ros2")
    # encoded by rosbags, put on rmw_zenoh's keys by a plain zenoh client (not our code)
    stamp = 1764000000.5
    publish = subprocess.run(
        [sys.executable, "publish_ros2.py", f"tcp/127.0.0.1:{station.port}", "3", str(stamp)],
        cwd=station.dir,
        env=station.env,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert publish.returncode == 0, publish.stderr
    labels = ("position", "fix", "temperature", "status")
    answer = station.latest(*labels, until=lambda a: all(_samples(a, x) for x in labels))
    [(position, valid, _)] = _samples(answer, "position")
    assert position == {"x": 12.0, "y": 20.0, "z": 1.5}  # geometry_msgs/PoseStamped
    assert valid == stamp + 2  # its header.stamp
    [(fix, valid, _)] = _samples(answer, "fix")  # sensor_msgs/NavSatFix, whole
    assert fix["latitude"] == pytest.approx(58.39002) and fix["altitude"] == 80.0
    assert fix["status"] == {"status": 0, "service": 1} and valid == stamp + 2
    [(temperature, valid, available)] = _samples(answer, "temperature")  # std_msgs/Float64
    assert temperature == 23.0 and valid == available  # no header: its arrival
    assert _samples(answer, "status")[0][0] == "ok 2"  # std_msgs/String
    out, err = station.stop()
    [status] = [r for r in _stats(out) if r.get("input") == "ros2 /station/status"]
    assert status["received"] == 4 and status["samples"] == 3
    assert list(status["bad"]) == ["not-cdr"] and "std_msgs/msg/String" in err


@pytest.mark.timeout(90)
def test_node_example_rosbag2_and_mcap_files_replayed(station: Station) -> None:
    # the recordings are written by rosbags (rosbag2) and mcap, not by our code
    made = subprocess.run(
        [sys.executable, "make_bag.py"],
        cwd=station.dir,
        env=station.env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert made.returncode == 0, made.stderr
    station.start("rosbag")
    answer = station.latest("position", until=lambda a: _samples(a, "position")[0][0]["x"] == 19.0)
    history = station.dyknow("ask", "position", "temperature", "-p", "station", "--from", "0")
    positions = _samples(history, "position")
    assert [p[0]["x"] for p in positions] == [10.0 + n for n in range(10)]
    # recorded pace: the last arrives at least the recorded 0.9 s after the first (later
    # when the node is slow), valid times as stamped
    assert positions[-1][2] - positions[0][2] >= 0.9 - 1e-3
    assert [p[1] for p in positions] == [pytest.approx(1764000000 + 0.1 * n) for n in range(10)]
    temperatures = _samples(history, "temperature")  # from the MCAP file, as fast as possible
    assert [t[0] for t in temperatures] == [21.0 + n for n in range(10)]
    assert temperatures[0][1] == 1764000000.0  # no header: the recorded log time
    assert answer
