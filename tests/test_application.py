"""A node's own application (docs/application.md): the config checked at start, messages mapped."""

from __future__ import annotations

import asyncio
import contextlib
import csv
import gc
import io
import itertools
import json
import logging
import re
import shutil
import subprocess
import sys
import time
import uuid
import weakref
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any
from unittest.mock import ANY

import pytest
from _node_example import Station, _samples, _stats

from dyknow_core import DyKnowInstance
from federation._inputs import ZenohInput, input_runner
from federation._outputs import ZenohOutput, output_runner
from federation.cli import main

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "node"


@pytest.fixture
def station(tmp_path: Path) -> Path:
    """examples/node copied, with keys; the file-input station's config."""
    from agents.keys import gen_keys, trust_keys
    from agents.transports import free_tcp_port

    d = tmp_path / "node"
    shutil.copytree(EXAMPLE, d)
    # a port and a federation of its own: a node another test runs meanwhile (another
    # worker) must not take the example's port, nor see this one
    federation = f"weather-{uuid.uuid4().hex[:8]}"
    port = free_tcp_port()
    for conf in d.glob("*.toml"):
        text = conf.read_text().replace("127.0.0.1:7450", f"127.0.0.1:{port}")
        conf.write_text(text.replace('federation = "weather"', f'federation = "{federation}"'))
    pub = gen_keys("station", d / "keys")[2]
    trust_keys(d / "keys" / "trust.json", [pub], federation=federation)
    return d / "station-file.toml"


def _node(config: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(["node", "--config", str(config)])
    return code, capsys.readouterr().err


def test_kpl_errors_stop_the_node_with_file_line_col(
    station: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    kpl = station.parent / "weather.kpl"
    kpl.write_text(kpl.read_text().replace("inputs wx/wind", "inputs wx/gust"))
    code, err = _node(station, capsys)
    assert code == 2
    assert f"{station}: application: the KPL file does not check:" in err
    assert f"{kpl}:7:12: unknown label 'wx/gust'" in err and "Traceback" not in err


def test_a_cu_that_does_not_import_is_named_with_its_line(
    station: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    kpl = station.parent / "weather.kpl"
    kpl.write_text(kpl.read_text().replace("weather_units:to_kmh", "weather_units:to_mph"))
    code, err = _node(station, capsys)
    assert code == 2
    assert f"{kpl}:6:1: cu 'kmh': weather_units:to_mph: AttributeError" in err


def test_input_and_output_labels_are_checked_at_start(
    station: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = station.read_text()
    station.write_text(text.replace('temperature = "wx/temperature"', 'temperature = "wx/state"'))
    code, err = _node(station, capsys)
    assert code == 2 and "inputs[0].fields: 'wx/state' is computed here, not a source" in err
    station.write_text(text.replace('temperature = "wx/temperature"', 'temperature = "wx/t"'))
    code, err = _node(station, capsys)
    assert code == 2 and "inputs[0].fields: no source 'wx/t'" in err
    station.write_text(text + '\n[[outputs]]\nkind = "zenoh"\nkey = "x"\nlabels = ["wx/nope"]\n')
    code, err = _node(station, capsys)
    assert code == 2 and "outputs[0].labels: no stream 'wx/nope' here" in err


def test_a_mapping_entry_of_no_stream_is_warned_about_at_start(tmp_path: Path) -> None:
    # a typo in the mapping: the node starts (a stream may appear later), but says so
    station = Station(tmp_path)
    labels = station.dir / "station-labels.toml"
    good = labels.read_text()
    try:
        station.start("python")
        assert "mapping" not in station.stop()[1]  # the example maps only its streams
        labels.write_text(good.replace('"wx/temperature"', '"wx/temprature"'))
        station.start("python")
        err = station.stop()[1]
    finally:
        station.stop()
    assert err.splitlines() == [
        "station-python.toml: mapping: station-labels.toml: labels.temperature: warning: "
        "no stream 'wx/temprature' here yet (a label the application lacks?): asking for "
        "'temperature' is refused until one appears"
    ]


@pytest.mark.timeout(90)
def test_a_unit_of_the_application_that_raises_is_said_and_counted(tmp_path: Path) -> None:
    # docs/application.md, "application": a CU that raises on a sample skips it, the node
    # goes on, and the user, who wrote no Python of the node, is told which one and why
    station = Station(tmp_path)
    (station.dir / "calm.jsonl").write_text(
        "".join(json.dumps({"wind": w}) + "\n" for w in (3, "calm", "calm", 5))
    )
    config = (station.dir / "station-python.toml").read_text().split("[[inputs]]")[0]
    (station.dir / "station-calm.toml").write_text(
        config + '[[inputs]]\nkind = "file"\npath = "calm.jsonl"\npace = "fast"\n'
        'fields = {wind = "wx/wind"}\n'
    )
    try:
        station.start("calm")
        station.follow_stderr()
        assert station.said("process 'kmh' failed (#2)", within=20.0)
        # the readings around the bad ones still went through the unit
        answer = station.dyknow("ask", "wind-speed-kmh", "-p", "station")
        assert answer["wind-speed-kmh"]["samples"][0][0] == 18.0  # 5 m/s
        out, err = station.stop()
    finally:
        station.stop()
    assert err.splitlines() == [
        "WARNING federation._application: application weather.kpl: process 'kmh' failed "
        f"(#{n}): TypeError: can't multiply sequence by non-int of type 'float'; that "
        "sample is skipped"
        for n in (1, 2)
    ]
    assert 'dyknow node: {"application": "weather.kpl", "failed": {"kmh": 2}}' in out


def test_a_unit_failing_on_every_reading_is_said_within_a_bound(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # docs/application.md, "application": the first 5 failures of each process, then one
    # in 1000, all counted; a process that is not the application's is not its to tell
    from types import SimpleNamespace

    from federation._application import NodeApplication

    platform = SimpleNamespace(config=SimpleNamespace(application=Path("weather.kpl")))
    app = NodeApplication(platform, "station.toml")  # type: ignore[arg-type]
    inst = DyKnowInstance("t")
    wind = inst.add_source("wx/wind")
    inst.add_cu("kmh", lambda w: w * 3.6, ["wx/wind"], "wx/kmh")
    inst.add_cu("import[x]", lambda w: w * 1.0, ["wx/wind"], "wx/other")
    app.kpl = SimpleNamespace(processes=["kmh"])  # type: ignore[assignment]
    inst.on_failure(app._failed)
    with caplog.at_level("WARNING", logger="federation._application"):
        for _ in range(2500):
            wind.push("calm")
    told = [r.getMessage().split(" failed ")[1].split(":")[0] for r in caplog.records]
    assert told == ["(#1)", "(#2)", "(#3)", "(#4)", "(#5)", "(#1000)", "(#2000)"]
    assert app.stats() == [{"application": "weather.kpl", "failed": {"kmh": 2500}}]


def test_a_units_error_is_said_on_one_bounded_line(caplog: pytest.LogCaptureFixture) -> None:
    # the error of a unit often quotes the value it could not take, and that value came
    # from outside (an MQTT message may be megabytes, a line break may forge a log line):
    # the warning shows its start, on one line
    from types import SimpleNamespace

    from federation._application import NodeApplication

    def to_kmh(wind: Any) -> float:
        raise ValueError(f"not a speed: {wind}")

    platform = SimpleNamespace(config=SimpleNamespace(application=Path("weather.kpl")))
    app = NodeApplication(platform, "station.toml")  # type: ignore[arg-type]
    inst = DyKnowInstance("t")
    wind = inst.add_source("wx/wind")
    inst.add_cu("kmh", to_kmh, ["wx/wind"], "wx/kmh")
    app.kpl = SimpleNamespace(processes=["kmh"])  # type: ignore[assignment]
    inst.on_failure(app._failed)
    with caplog.at_level("WARNING", logger="federation._application"):
        wind.push("calm\nERROR forged" + "x" * 100_000)
    [said] = [r.getMessage() for r in caplog.records]
    assert "failed (#1): ValueError: not a speed: calm\\x0aERROR forgedxxx" in said, said[:300]
    assert len(said) < 500 and said.endswith(" left out); that sample is skipped"), said[-100:]


@pytest.mark.timeout(90)
def test_an_input_that_fails_for_good_is_named_as_an_input(tmp_path: Path) -> None:
    # docs/application.md: `input python feed:readings stopped: <the reason in words>`,
    # and the node goes on
    station = Station(tmp_path)
    (station.dir / "probe.py").write_text(
        "async def soil():\n"
        "    yield {'temperature': 12.5}\n"
        "    raise ValueError(\"the reading 'x' is no number\")\n"
    )
    config = (station.dir / "station-python.toml").read_text().split("[[inputs]]")[0]
    (station.dir / "station-probe.toml").write_text(
        config + '[[inputs]]\nkind = "python"\nentry = "probe:soil"\n'
        'fields = {temperature = "wx/temperature"}\n'
    )
    try:
        station.start("probe")
        station.follow_stderr()
        assert station.said("stopped", within=20.0)
        answer = station.dyknow("ask", "temperature", "-p", "station")  # the node goes on
        assert answer["temperature"]["samples"][0][0] == 12.5
        _, err = station.stop()
    finally:
        station.stop()
    assert err.splitlines() == [
        "ERROR federation._application: input python probe:soil stopped: the reading 'x' "
        "is no number"
    ]


def _gusts(directory: Path, local: str) -> None:
    """A vocabulary pattern, its mapping to ``local``, an input making 'gusts/{station}/kmh'."""
    with (directory / "weather.toml").open("a") as f:
        f.write('"{object}-gust" = "the gusts at a station, km/h"\n')
    with (directory / "station-labels.toml").open("a") as f:
        f.write(f'"{{object}}-gust" = "{local}"\n')
    config = directory / "station-python.toml"
    config.write_text(config.read_text() + 'gust = "gusts/{station}/kmh"\n')


def test_a_mapping_pattern_nothing_can_match_is_warned_about_at_start(tmp_path: Path) -> None:
    # a typo in a pattern's local side: no stream yet is normal for a pattern, but no
    # label an input makes matching it either means it never will
    good = Station(tmp_path / "good")
    _gusts(good.dir, "gusts/{object}/kmh")
    typo = Station(tmp_path / "typo")
    _gusts(typo.dir, "gust/{object}/kmh")
    try:
        good.start("python")
        assert good.stop()[1] == ""  # a pattern an input's label template matches: silent
        typo.start("python")
        err = typo.stop()[1]
    finally:
        good.stop()
        typo.stop()
    assert err.splitlines() == [
        'station-python.toml: mapping: station-labels.toml: labels."{object}-gust": warning: '
        "local pattern 'gust/{object}/kmh' can match no stream here nor any label an input, "
        "import or class feature makes (did you mean 'gusts/{station}/kmh'?): no "
        "'{object}-gust' label is served until one does"
    ]


def test_a_mapping_pattern_a_class_feature_makes_is_not_warned_about(tmp_path: Path) -> None:
    # the anchoring creates a stream per feature of each object it makes, at run time:
    # a pattern matching a feature's label pattern is no typo
    station = Station(tmp_path)
    with (station.dir / "weather.kpl").open("a") as f:
        f.write(
            "\nsource blobs\n"
            "class VisionObject {\n"
            '    feature pixel = "vo/{id}/pixel"\n'
            '    create "pixel > 0" from blobs\n'
            "}\n"
            "anchoring every 1\n"
        )
    with (station.dir / "weather.toml").open("a") as f:
        f.write('"{object}-pixel" = "a seen object\'s pixel"\n')
    with (station.dir / "station-labels.toml").open("a") as f:
        f.write('"{object}-pixel" = "vo/{object}/pixel"\n')
    try:
        station.start("python")
    finally:
        err = station.stop()[1]
    assert err == ""


@pytest.mark.parametrize(
    ("semantic", "local", "refusal"),
    [
        (  # a misspelt vocabulary pattern: refused, naming what it could be
            "{object}-gusts",
            "gusts/{object}/kmh",
            'labels."{object}-gusts": not in the vocabulary weather '
            "(did you mean '{object}-gust'?)",
        ),
        (  # a placeholder on one side only
            "{object}-gust",
            "gusts/{station}/kmh",
            "labels.\"{object}-gust\": local pattern 'gusts/{station}/kmh' must have "
            "exactly {object}",
        ),
    ],
)
def test_a_mapping_pattern_certainly_wrong_stops_the_node(
    station: Path, capsys: pytest.CaptureFixture[str], semantic: str, local: str, refusal: str
) -> None:
    _gusts(station.parent, "gusts/{object}/kmh")
    labels = station.parent / "station-labels.toml"
    labels.write_text(labels.read_text().replace('"{object}-gust" = "gusts/{object}/kmh"', ""))
    with labels.open("a") as f:
        f.write(f'"{semantic}" = "{local}"\n')
    code, err = _node(station, capsys)
    assert code == 2, err
    assert f"mapping: {labels}: {refusal}" in err, err
    assert "Traceback" not in err


def test_config_keys_of_inputs_are_named(station: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = station.read_text()
    station.write_text(text.replace('kind = "file"', 'kind = "ftp"', 1))
    code, err = _node(station, capsys)
    kinds = "'zenoh', 'mqtt', 'file', 'python', 'ros2', 'rosbag'"
    assert code == 2 and f"inputs[0].kind: expected {kinds}" in err
    station.write_text(text.replace('pace = "fast"', 'pace = "fast"\nspeeed = 2'))
    code, err = _node(station, capsys)
    assert code == 2 and "inputs[1].speeed: unknown key" in err
    station.write_text(
        text + '\n[[inputs]]\nkind = "python"\nentry = "nowhere:gen"\nfields = {"." = "wx/wind"}\n'
    )
    code, err = _node(station, capsys)
    assert code == 2 and "inputs[2].entry: nowhere:gen: ModuleNotFoundError" in err
    station.write_text(text.replace('path = "observations.csv"', 'path = "observation.csv"'))
    code, err = _node(station, capsys)
    missing = station.parent / "observation.csv"
    assert code == 2 and f"inputs[1].path: {missing}: no such file" in err
    station.write_text(text.replace('pace = "fast"', 'pace = "fast"\nmax_streams = 0'))
    code, err = _node(station, capsys)
    assert code == 2 and "inputs[1].max_streams: Input should be greater than or equal to 1" in err
    assert "Traceback" not in err


async def test_messages_map_to_samples_and_bad_ones_are_counted() -> None:
    async with DyKnowInstance("t") as inst:
        inst.add_source("car/car1/speed")
        settings = ZenohInput(
            kind="zenoh",
            key="cars/*",
            fields={"speed": "car/{id}/speed", "pose.x": "car/{id}/x"},
            time="stamp",
            time_unit="ms",
            create=True,
        )
        runner = input_runner(settings, inst)
        handle = runner.mapper.handle
        handle({"id": "car1", "speed": 12.5, "stamp": 1_700_000_000_123})
        handle({"id": "car2", "pose": {"x": 3.0}})  # no stamp: valid at arrival
        handle({"id": "car3", "speed": 1.0, "stamp": "noon"})
        handle({"speed": 2.0})  # no id for the label
        handle({"id": "car1"})  # none of the fields
        handle({"id": {"nested": 1}, "speed": 3.0})
        handle(["not", "a", "mapping"])
        assert inst.latest("car/car1/speed").samples[0].valid_time == 1_700_000_000_123_000_000
        assert inst.latest("car/car1/speed").samples[0].value == 12.5
        x = inst.latest("car/car2/x").samples[0]  # created on first use (create = true)
        assert x.value == 3.0 and x.valid_time == x.available_time
        stats = runner.stats.as_dict()
        assert stats["received"] == 7 and stats["samples"] == 2
        assert stats["bad"] == {"bad-time": 1, "no-label-field": 2, "no-field": 2}
        assert runner.mapper.decode(b"\x81\xa1a\x01", "msgpack") == {"a": 1}


async def test_a_bad_messages_warning_is_one_bounded_line_whatever_it_quotes(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # what was wrong often quotes the message (a time field's value, a stream's refusal of
    # a value): a megabyte's value would be logged whole, a newline forge a log line
    async with DyKnowInstance("t") as inst:
        inst.add_source("wx/t")
        runner = input_runner(
            ZenohInput(kind="zenoh", key="k", fields={"v": "wx/t"}, time="stamp"), inst
        )
        with caplog.at_level("WARNING", logger="federation._inputs"):
            runner.mapper.handle({"v": 1, "stamp": "z" * 100_000})
            runner.mapper.bad("refused", "ValueError: no\nFAKE: a forged line")
    lines = [r.getMessage() for r in caplog.records if r.name == "federation._inputs"]
    assert len(lines) == 2 and all("\n" not in line for line in lines), lines
    assert len(lines[0]) < 400 and "(100026 characters, 99826 left out)" in lines[0], lines[0]
    assert lines[0].startswith("input zenoh k: bad message #1 (bad-time): stamp = 'zzz")
    assert lines[1].endswith("ValueError: no\\x0aFAKE: a forged line"), lines[1]
    assert runner.stats.as_dict()["bad"] == {"bad-time": 1, "refused": 1}


async def test_an_output_stopped_leaves_no_task_of_its_own() -> None:
    class Session:  # the node's zenoh session, as the output uses it
        def __init__(self) -> None:
            self.puts: list[tuple[str, bytes]] = []
            self.put_once = asyncio.Event()

        def put(self, key: str, payload: Any) -> None:
            self.puts.append((key, payload))
            self.put_once.set()

    async with DyKnowInstance("t") as inst:
        src = inst.add_source("wx/temp")
        out = output_runner(ZenohOutput(kind="zenoh", key="out/{label}", labels=["wx/*"]), inst)
        session = Session()
        running = asyncio.create_task(out.run(session), name="output")
        async with asyncio.timeout(5):
            while not session.put_once.is_set():  # pushed until the output follows the stream
                src.push(21.5)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(session.put_once.wait(), 0.01)
        assert session.puts[0][0] == "out/wx/temp"
        running.cancel()
        await asyncio.wait([running])
        # (the instance's own timer tasks come and go: only the output's are compared)
        assert not [t for t in asyncio.all_tasks() if t.get_name().startswith("output")]


async def test_a_pattern_output_publishes_a_new_streams_first_sample() -> None:
    # docs/application.md, "Outputs": a glob pattern picks up streams that appear later,
    # from their first sample (an input with create = true makes the stream as its first
    # message comes and pushes that message at once)
    class Session:
        def __init__(self) -> None:
            self.puts: asyncio.Queue[tuple[str, dict[str, Any]]] = asyncio.Queue()

        def put(self, key: str, payload: bytes) -> None:
            self.puts.put_nowait((key, json.loads(payload)))

    async with DyKnowInstance("t") as inst:
        moisture = inst.add_source("soil/moisture")
        settings = ZenohOutput(kind="zenoh", key="out/{label}", labels=["leaf/*/temp"])
        out = output_runner(settings, inst)
        session = Session()
        running = asyncio.create_task(out.run(session), name="output")
        try:
            await asyncio.sleep(0)  # the output starts following before the streams come
            for sensor, temp in (("s1", 19.5), ("s2", 18.0)):
                inst.add_source(f"leaf/{sensor}/temp").push(temp)
            moisture.push(25)  # not the output's
            async with asyncio.timeout(5):
                got = [await session.puts.get() for _ in range(2)]
            assert [(k, p["value"]) for k, p in got] == [
                ("out/leaf/s1/temp", 19.5),
                ("out/leaf/s2/temp", 18.0),
            ]
            # a stream removed and made anew under the same label is followed again
            inst.remove_process("source:leaf/s1/temp")
            inst.add_source("leaf/s1/temp").push(20.0)
            async with asyncio.timeout(5):
                assert await session.puts.get() == (
                    "out/leaf/s1/temp",
                    {"label": "leaf/s1/temp", "value": 20.0, "valid": ANY, "available": ANY},
                )
            assert session.puts.empty()  # the moisture, not matched, was not published
        finally:
            running.cancel()
            await asyncio.wait([running])


async def test_a_zenoh_output_publishes_no_stream_whose_key_would_be_a_wildcard_or_no_key(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # docs/application.md, "Outputs": a stream named from outside (create = true) whose
    # key would hold `$*` (a put reaching other keys' subscribers) or another `$` (no zenoh
    # key: the put raises, which stopped the output) is not published, counted and said
    class Session:
        def __init__(self) -> None:
            self.puts: asyncio.Queue[tuple[str, Any]] = asyncio.Queue()

        def put(self, key: str, payload: bytes) -> None:
            self.puts.put_nowait((key, json.loads(payload)["value"]))

    async with DyKnowInstance("t") as inst:
        settings = ZenohOutput(kind="zenoh", key="out/{label}", labels=["soil/*/m"])
        out = output_runner(settings, inst)
        session = Session()
        running = asyncio.create_task(out.run(session), name="output")
        try:
            await asyncio.sleep(0)  # the output starts following before the streams come
            for probe, value in (("p$*", 1), ("p$x", 2), ("p\ud800", 3), ("p1", 4)):
                inst.add_source(f"soil/{probe}/m").push(value)
            async with asyncio.timeout(5):
                assert await session.puts.get() == ("out/soil/p1/m", 4)
            assert session.puts.empty() and not running.done()
        finally:
            running.cancel()
            await asyncio.wait([running])
    assert (out.published, out.refused) == (1, 3)
    said = [r.getMessage() for r in caplog.records if "not published" in r.getMessage()]
    assert said == [
        "output zenoh out/{label}: stream 'soil/p$*/m' not published: its key 'out/soil/p$*/m' "
        "is a zenoh wildcard ($*, *): its put would reach other keys (#1)",
        "output zenoh out/{label}: stream 'soil/p$x/m' not published: its key 'out/soil/p$x/m' "
        "is no zenoh key (Invalid Key Expr `out/soil/p$x/m`: `$` is only allowed in `$*`) (#2)",
        "output zenoh out/{label}: stream 'soil/p\\ud800/m' not published: its key "
        "'out/soil/p\\ud800/m' is not UTF-8 (a lone surrogate) (#3)",
    ]


async def test_a_pattern_output_keeps_no_stream_that_was_removed() -> None:
    # streams come and go on a running node (an import that ended and began again, an
    # object a gateway removed): an output following them must not keep the removed ones,
    # their caches with them, for as long as it runs
    class Session:
        def __init__(self) -> None:
            self.puts: asyncio.Queue[str] = asyncio.Queue()

        def put(self, key: str, payload: bytes) -> None:
            self.puts.put_nowait(key)

    async with DyKnowInstance("t") as inst:
        out = output_runner(ZenohOutput(kind="zenoh", key="out/{label}", labels=["leaf/*"]), inst)
        running = asyncio.create_task(out.run(session := Session()), name="output")
        try:
            await asyncio.sleep(0)  # the output starts following before the streams come
            gone = []
            for n in range(3):
                src = inst.add_source("leaf/a")
                src.push(n)
                async with asyncio.timeout(5):
                    assert await session.puts.get() == "out/leaf/a"
                gone.append(weakref.ref(src.generator))
                inst.remove_process(src.name)
                del src
            gc.collect()
            assert [ref() for ref in gone] == [None, None, None]
        finally:
            running.cancel()
            await asyncio.wait([running])


async def test_an_output_run_again_follows_its_streams_again() -> None:
    # an output's run ends (cancelled with its node's application) and may be run again:
    # its subscriptions ended with the first run, so the second follows anew
    class Session:
        def __init__(self) -> None:
            self.puts: asyncio.Queue[str] = asyncio.Queue()

        def put(self, key: str, payload: bytes) -> None:
            self.puts.put_nowait(key)

    async with DyKnowInstance("t") as inst:
        src = inst.add_source("leaf/a")
        out = output_runner(ZenohOutput(kind="zenoh", key="out/{label}", labels=["leaf/*"]), inst)
        session = Session()
        for _ in range(2):
            running = asyncio.create_task(out.run(session), name="output")
            try:
                await asyncio.sleep(0)  # the output follows the stream
                src.push(1.0)
                async with asyncio.timeout(5):
                    assert await session.puts.get() == "out/leaf/a"
            finally:
                running.cancel()
                await asyncio.wait([running])


def test_a_zenoh_input_on_an_mqtt_node_needs_its_own_connect(
    station: Path, capsys: pytest.CaptureFixture[str], mosquitto: tuple[str, int]
) -> None:
    host, port = mosquitto
    text = (station.parent / "station-zenoh.toml").read_text()
    text = re.sub(
        r'mode = "peer"\nlisten = \["tcp/127\.0\.0\.1:\d+"\]',
        f'kind = "mqtt"\nhost = "{host}"\nport = {port}',
        text,
    )
    station.write_text(text)
    code, err = _node(station, capsys)
    assert code == 2 and "inputs[0].connect: missing: the node's transport is not zenoh" in err


async def test_a_csv_field_over_the_limit_costs_its_row_only(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from federation._inputs import FileInput

    path = tmp_path / "wx.csv"
    big = "x" * (129 * 1024)
    path.write_text(f"time,temp\n1,20.5\n2,{big}\n3,21.5\n4,1,extra\n5,22.5\n")
    async with DyKnowInstance("t") as inst:
        inst.add_source("wx/temp")
        settings = FileInput(kind="file", path=path, pace="fast", fields={"temp": "wx/temp"})
        runner = input_runner(settings, inst)
        with caplog.at_level("WARNING", logger="federation._inputs"):
            await asyncio.wait_for(runner.run(None), 10)
        assert runner.stats.as_dict()["bad"] == {"field-too-large": 1, "not-csv": 1}
        assert runner.stats.samples == 3
        assert f"{path}:3: a field over the 131072-character limit" in caplog.text
        assert f"{path}:5: 3 cells" in caplog.text
        path.write_text(f"time,{big}\n1,20.5\n")  # no header: no row can be read
        runner = input_runner(settings, inst)
        await asyncio.wait_for(runner.run(None), 10)
        assert runner.stats.as_dict()["bad"] == {"field-too-large": 1}
        assert f"{path}:1: a field over the 131072-character limit; no header row" in caplog.text


async def _looped_file(path: Path, n: int, **play: Any) -> list[tuple[int, int]]:
    """The (valid, available) times of the first ``n`` (or a few more) samples a looped file
    input (``shift = "now"``, its time in ``t``) pushes, played as ``play`` says."""
    from federation._inputs import FileInput

    got: list[tuple[int, int]] = []
    enough = asyncio.Event()

    def on_batch(batch: list[Any]) -> None:
        got.extend((tv, ta) for _, tv, ta in batch)
        if len(got) >= n:
            enough.set()

    async with DyKnowInstance("t") as inst:
        inst.add_source("wx/temp")
        inst.subscribe("wx/temp", callback=on_batch)
        settings = FileInput(
            kind="file",
            path=path,
            loop=True,
            shift="now",
            time="t",
            fields={"temp": "wx/temp"},
            **play,
        )
        task = asyncio.create_task(input_runner(settings, inst).run(None))
        try:
            await asyncio.wait_for(enough.wait(), 20)
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
    return got


@pytest.mark.parametrize("speed", [1.0, 2.0])
async def test_a_looped_file_gives_each_pass_times_after_the_last(
    tmp_path: Path, speed: float
) -> None:
    """``loop = true``, ``shift = "now"``: valid times never go back at a pass's seam.

    Before, each pass started its valid times at the wall clock: behind the last pass's
    latest when its last sleep woke early (by ~0.2 ms) or ``speed`` ran them ahead.
    """
    path = tmp_path / "wx.jsonl"
    path.write_text("".join(f'{{"t": {k * 0.01}, "temp": {k}}}\n' for k in range(3)))
    got = await _looped_file(path, 12, speed=speed)
    valid = [tv for tv, _ in got]
    assert all(b > a for a, b in itertools.pairwise(valid)), valid
    if speed == 1.0:  # valid times are when each sample was due: none after its arrival
        assert all(tv <= ta for tv, ta in got), got


def _zenoh(**settings: str) -> Any:
    """A zenoh session on this host only (no scouting)."""
    import zenoh

    config = zenoh.Config()
    for key, value in settings.items():
        config.insert_json5(key.replace("__", "/"), value)
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


async def test_a_ros2_input_on_a_wrong_topic_warns_once_naming_the_topics_there(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A ``ros2`` input whose topic nobody publishes says so once, naming the topics there."""
    import threading

    from agents.transports import free_tcp_port
    from federation import _ros
    from federation._inputs import Ros2Input

    monkeypatch.setattr(_ros, "SILENT_WARN", 0.2)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    node = _zenoh(mode='"peer"', listen__endpoints=json.dumps([endpoint]))
    ros = _zenoh(mode='"client"', connect__endpoints=json.dumps([endpoint]))
    stop = threading.Event()
    hash_ = "RIHS01_" + "0" * 64
    battery = ros.declare_publisher(f"0/robot/battery/std_msgs::msg::dds_::Float32_/{hash_}")
    # publishers as rmw_zenoh states them in the ROS graph: one publishing, one with no
    # message yet
    tokens = [
        ros.liveliness().declare_token(
            f"@ros2_lv/0/{ros.zid()}/0/{n}/MP/%/%/driver/{topic}/{kind}/{hash_}/::,10:,:,:,,"
        )
        for n, topic, kind in (
            (10, "%robot%battery", "std_msgs::msg::dds_::Float32_"),
            (11, "%robot%pose", "geometry_msgs::msg::dds_::PoseStamped_"),
        )
    ]
    pulled: list[bool] = []  # whether the messages were ever asked for by the node

    def publish() -> None:
        while not stop.wait(0.05):
            battery.put(b"\x00\x01\x00\x00\x00\x00\xa0\x41")
            if battery.matching_status.matching:
                pulled.append(True)

    # the graph's tokens reach the node's session before the input asks (0.2 s after its
    # start): on a busy machine they could come later, and the warning say "none seen"
    deadline = time.monotonic() + 20
    while len(list(node.liveliness().get("@ros2_lv/0/**", timeout=1.0))) < len(tokens):
        assert time.monotonic() < deadline, "the ROS graph's tokens never reached the node"
    publisher = threading.Thread(target=publish)
    publisher.start()
    try:
        async with DyKnowInstance("t") as inst:
            inst.add_source("b")
            settings = Ros2Input(kind="ros2", topic="/robot/batery", fields={"data": "b"})
            runner = _ros.ros_runner(settings, inst)
            warned = asyncio.Event()
            handler = logging.Handler(logging.WARNING)
            handler.emit = lambda record: warned.set()  # type: ignore[method-assign]
            ros_log = logging.getLogger("federation._ros")
            ros_log.addHandler(handler)
            with caplog.at_level("WARNING", logger="federation._ros"):
                task = asyncio.create_task(runner.run(node))
                try:
                    await asyncio.wait_for(warned.wait(), 20)
                finally:
                    ros_log.removeHandler(handler)
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await task
        assert (
            "input ros2 /robot/batery: no message on topic '/robot/batery' in 0.2 s (zenoh key "
            "0/robot/batery/*/*); topics published in ROS domain 0: '/robot/battery' "
            "(std_msgs/msg/Float32), '/robot/pose' (geometry_msgs/msg/PoseStamped)"
        ) in caplog.text
        assert caplog.text.count("no message on topic") == 1
        # the graph's keys only: the domain's messages never pulled into the node
        assert not pulled
    finally:
        stop.set()
        publisher.join()
        for token in tokens:
            token.undeclare()
        ros.close()
        node.close()


def _graph_reader(endpoint: str, publishers: int, conn: Connection) -> None:
    """Child: what ``ros_topics`` reads of ROS domain 0 through ``endpoint``, once all came."""
    from federation._ros import ros_topics

    node = _zenoh(mode='"peer"', connect__endpoints=json.dumps([endpoint]))
    try:
        deadline = time.monotonic() + 30  # the link may come up after the first query
        calls = 1
        while len(topics := ros_topics(node, 0)) < publishers and time.monotonic() < deadline:
            calls += 1
        conn.send((topics, calls))
    finally:
        node.close()
        conn.close()


@pytest.mark.timeout(120)
def test_a_ros_graph_of_hundreds_of_tokens_is_read_whole() -> None:
    """Before, over 256 matching tokens (zenoh's default handler's room) hung the reader.

    zenoh answers the tokens it knows inside the liveliness get, holding its session's
    lock, so the reader's session stayed stuck for ever; read in a spawned child so that a
    hang fails this test (bounded) instead of hanging it.
    """
    import multiprocessing

    from agents.transports import free_tcp_port

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    ros = _zenoh(mode='"peer"', listen__endpoints=json.dumps([endpoint]))
    hash_ = "RIHS01_" + "0" * 64
    pose = "geometry_msgs::msg::dds_::PoseStamped_"

    def token(domain: int, n: int, kind: str, topic: str) -> Any:
        node = f"@ros2_lv/{domain}/{ros.zid()}/0/{n}/{kind}/%/%/r{n}"
        key = f"{node}/{topic}/{pose}/{hash_}/::,10:,:,:,,"
        return ros.liveliness().declare_token(key)

    # 300 publishers, 20 subscriptions (not listed) and another domain's publishers
    publishers = 300
    tokens = [token(0, n, "MP", f"%robot{n}%pose") for n in range(publishers)]
    tokens += [token(0, n, "MS", f"%heard{n}") for n in range(20)]
    tokens += [token(1, n, "MP", f"%elsewhere{n}") for n in range(5)]
    ctx = multiprocessing.get_context("spawn")
    mine, theirs = ctx.Pipe(duplex=False)
    reader = ctx.Process(target=_graph_reader, args=(endpoint, publishers, theirs))
    reader.start()
    theirs.close()
    try:
        # a spawned interpreter imports zenoh and DyKnow first: generous on a busy box
        assert mine.poll(60), f"ros_topics did not return within 60 s ({len(tokens)} tokens)"
        topics, calls = mine.recv()
        reader.join(10)
        assert reader.exitcode == 0
    finally:
        if reader.is_alive():
            reader.kill()
            reader.join()
        mine.close()
        for t in tokens:
            t.undeclare()
        ros.close()
    want = {f"/robot{n}/pose": "geometry_msgs/msg/PoseStamped" for n in range(publishers)}
    assert topics == want, f"after {calls} graph queries: {len(topics)} topics"


async def test_a_quoted_csv_field_over_the_limit_costs_all_its_lines(tmp_path: Path) -> None:
    from federation._inputs import _csv_rows

    big = "x" * (csv.field_size_limit() + 10)
    text = f'time,temp\n1,20.5\n2,"abc\n{big}\nlast,9"\n3,"a ""b""\nc"\n4,21.5\n5,"{big}\n'
    rows = _csv_rows(io.StringIO(text, newline=""), tmp_path / "wx.csv")
    bad = [r for r in rows if not isinstance(r, dict)]
    assert [r for r in rows if isinstance(r, dict)] == [
        {"time": 1, "temp": 20.5},
        {"time": 3, "temp": 'a "b"\nc'},
        {"time": 4, "temp": 21.5},
    ]
    # each error names its row's first line; an unclosed quote is the rest of the file
    assert [(r.reason, r.detail.split(": ")[0]) for r in bad] == [
        ("field-too-large", f"{tmp_path / 'wx.csv'}:3"),
        ("field-too-large", f"{tmp_path / 'wx.csv'}:9"),
    ]


def test_an_mcap_file_without_the_topic_names_the_topics_it_has(tmp_path: Path) -> None:
    """As a rosbag2 directory does: the user sees which topic they meant."""
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    from federation._ros import _read_bag

    store = get_typestore(Stores.ROS2_HUMBLE)
    float32 = "std_msgs/msg/Float32"
    path = tmp_path / "run.mcap"
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2", library="test")
        msgdef, _ = store.generate_msgdef(float32)
        schema = writer.register_schema(float32, "ros2msg", msgdef.encode())
        for topic in ("/battery", "/odom"):
            channel = writer.register_channel(topic, "cdr", schema)
            data = bytes(store.serialize_cdr(store.types[float32](data=1.0), float32))
            writer.add_message(channel, 1, data, 1)
        writer.finish()
    with pytest.raises(ValueError, match=r"no topic '/odm' \(it has /battery, /odom\)"):
        _read_bag(path, "/odm")
    assert len(_read_bag(path, "/odom")) == 1


@pytest.mark.parametrize("pace", ["fast", "recorded"])
async def test_rosbag_inputs_on_one_recording_share_its_start(tmp_path: Path, pace: str) -> None:
    """``shift = "now"``: messages recorded at one instant get one valid time, on any topic.

    Before, each input on the file took its own "now" at its own first message: one
    recorded instant became valid times ~21 ms apart, or a topic's first message later.
    With ``pace = "recorded"`` they are paced from that shared start too: a topic starting
    later in the recording got valid times a gap ahead of its samples' arrival.
    """
    from types import SimpleNamespace

    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    from federation._application import NodeApplication
    from federation._inputs import RosbagInput

    store = get_typestore(Stores.ROS2_HUMBLE)
    float32 = "std_msgs/msg/Float32"
    path = tmp_path / "run.mcap"
    unit = 200_000_000  # the recorded gap (ns)
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2", library="test")
        msgdef, _ = store.generate_msgdef(float32)
        schema = writer.register_schema(float32, "ros2msg", msgdef.encode())
        channels = {t: writer.register_channel(t, "cdr", schema) for t in ("/a", "/b")}
        # /a from 1 unit on, /b from 2: the inputs' first messages differ by a gap
        for topic, n in (("/a", 1), ("/a", 2), ("/b", 2), ("/b", 3)):
            data = bytes(store.serialize_cdr(store.types[float32](data=n), float32))
            writer.add_message(channels[topic], n * unit, data, n * unit)
        writer.finish()
    inputs = [
        RosbagInput(
            kind="rosbag",
            path=path,
            topic=topic,
            pace=pace,  # type: ignore[arg-type]
            shift="now",
            fields={"data": f"bag/{topic[1:]}"},
        )
        for topic in ("/a", "/b")
    ]
    valid: dict[tuple[str, float], int] = {}
    arrived: dict[tuple[str, float], int] = {}
    enough = asyncio.Event()

    def on(label: str) -> Any:
        def on_batch(batch: list[Any]) -> None:
            now = time.time_ns()
            for v, tv, _ in batch:
                valid[label, v] = tv
                arrived[label, v] = now
            if len(valid) >= 4:
                enough.set()

        return on_batch

    async with DyKnowInstance("t") as inst:
        for label in ("bag/a", "bag/b"):
            inst.add_source(label)
            inst.subscribe(label, callback=on(label))
        config = SimpleNamespace(application=None, inputs=inputs, outputs=[])
        platform = SimpleNamespace(instance=inst, config=config, transport=None)
        async with NodeApplication(platform, "t.toml"):  # type: ignore[arg-type]
            await asyncio.wait_for(enough.wait(), 20)
    assert valid[("bag/a", 2.0)] == valid[("bag/b", 2.0)], valid
    assert valid[("bag/a", 2.0)] - valid[("bag/a", 1.0)] == unit, valid
    assert valid[("bag/b", 3.0)] - valid[("bag/b", 2.0)] == unit, valid
    if pace == "recorded":
        # none comes before its valid time (a slack for the clocks; the bug was a gap early)
        early = {k: (valid[k] - at) / 1e9 for k, at in arrived.items() if at < valid[k] - unit // 4}
        assert not early, early


@pytest.mark.timeout(120)
@pytest.mark.parametrize("command", ["console", "foxglove"])
def test_console_and_foxglove_say_what_the_application_received(
    tmp_path: Path, command: str
) -> None:
    """They run the node's application, so they end with its inputs' counts as a node does."""
    import signal
    import subprocess
    import sys

    station = Station(tmp_path)
    proc = subprocess.Popen(
        [sys.executable, "-m", "federation.cli", command, "-c", "station-file.toml", "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=station.dir,
        env=station.env,
    )
    assert proc.stdout is not None
    for line in proc.stdout:  # bounded by the test's timeout
        if "ready in federation" in line:
            break
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    rows = [json.loads(line.split(": ", 1)[1]) for line in out.splitlines() if ': {"' in line]
    inputs = {row["input"]: row for row in rows if "input" in row}
    assert "file observations.csv" in inputs and inputs["file observations.csv"]["samples"] > 0, (
        out + err
    )
    assert f"dyknow {command}: " + "{" in out and "Traceback" not in err


@pytest.mark.timeout(120)
@pytest.mark.parametrize("command", ["console", "foxglove"])
def test_a_console_port_in_use_is_named_with_the_option_to_change(
    tmp_path: Path, command: str
) -> None:
    import socket
    import subprocess
    import sys

    station = Station(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "federation.cli",
                command,
                "-c",
                "station-file.toml",
                "--port",
                str(port),
            ],
            capture_output=True,
            text=True,
            cwd=station.dir,
            env=station.env,
            timeout=60,
        )
    assert done.returncode == 1, done.stderr
    assert f"cannot serve on 127.0.0.1:{port}: the address is in use" in done.stderr
    assert "--port" in done.stderr and "Errno" not in done.stderr, done.stderr


async def test_a_message_without_the_fields_says_which_fields_it_has(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A misspelt field is seen at once beside the message's own (a CSV file's columns)."""
    async with DyKnowInstance("t") as inst:
        inst.add_source("lidar/range")
        settings = ZenohInput(kind="zenoh", key="k", fields={"min_rang": "lidar/range"})
        runner = input_runner(settings, inst)
        with caplog.at_level("WARNING"):
            runner.mapper.handle({"stamp": 1.0, "min_range": 2.0, "obstacle": False})
            runner.mapper.handle([1, 2])
        assert "none of the fields min_rang in the message (it has stamp, min_range, obstacle)" in (
            caplog.text
        )
        assert "none of the fields min_rang in the message (a list)" in caplog.text


async def test_an_input_that_stops_says_why_in_words(caplog: pytest.LogCaptureFixture) -> None:
    """Before: ``input … stopped: ValueError: …``, the Python class of the failure."""
    from federation._application import NodeApplication, in_words

    async def failing() -> None:
        raise ValueError("the reading 'x' is no number")

    with caplog.at_level("ERROR", logger="federation._application"):
        await NodeApplication._logged("input python feed:readings", failing())
    assert "input python feed:readings stopped: the reading 'x' is no number" in caplog.text
    assert "ValueError" not in caplog.text
    assert in_words(ConnectionResetError()) == "connection reset"
    assert in_words(TimeoutError()) == "timed out"
    assert in_words(FileNotFoundError(2, "No such file or directory", "/srv/x.jsonl")) == (
        "no such file or directory: /srv/x.jsonl"
    )
    assert in_words(KeyError("speed")) == "no 'speed' where one was needed"


def test_a_key_error_with_its_own_text_is_said_as_it_is() -> None:
    """UnknownLabelError is a KeyError: its message, not ``no "unknown label …" where …``."""
    from dyknow_core import UnknownLabelError
    from federation._application import in_words

    assert in_words(UnknownLabelError("speed", ["altitude"])) == (
        "unknown label 'speed' (known labels: altitude)"
    )


def test_a_superscript_digit_is_no_index_of_an_input_field() -> None:
    """``items.²`` names no index (``"²".isdigit()``, yet ``int`` refuses it): no field."""
    from federation._inputs import _MISSING, _get

    assert _get({"items": [1, 2, 3]}, "items.²") is _MISSING
    assert _get({"items": [1, 2, 3]}, "items.2") == 3


async def test_a_looped_file_played_fast_stays_near_the_wall_clock(tmp_path: Path) -> None:
    """``pace = "fast"``, ``shift = "now"``: each pass starts at now, never back past the last.

    Before, each pass started after the last one's latest: 100 passes of a 0.2 s file at
    once ran 20 s ahead of the wall clock; and a row earlier than the first fell back
    before the previous pass.
    """
    path = tmp_path / "wx.jsonl"
    times = [0.1, 0.0, 0.2]  # the second row earlier than the first
    path.write_text("".join(f'{{"t": {t}, "temp": {k}}}\n' for k, t in enumerate(times)))
    got = [tv for tv, _ in await _looped_file(path, 300, pace="fast")]
    ahead = (max(got) - time.time_ns()) / 1e9
    assert ahead < 1.0, ahead  # one pass's span (0.2 s) at most, and some slack
    passes = [got[i : i + 3] for i in range(0, len(got) - 2, 3)]
    assert all(min(b) > max(a) for a, b in itertools.pairwise(passes)), passes[:4]


async def test_a_csv_column_the_input_names_and_the_header_lacks_is_warned_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A misspelt column gives no sample and no bad message: the header check names it."""
    from federation._inputs import FileInput

    path = tmp_path / "loops.csv"
    path.write_text("time,segment,speed,flow\n1,s1,60,20\n2,s1,57,21\n")
    fields = {"speeed": "seg/{segment}/speed", "flow": "seg/{segmnt}/flow"}
    async with DyKnowInstance("t") as inst:
        settings = FileInput(
            kind="file", path=path, pace="fast", time="tme", create=True, fields=fields
        )
        runner = input_runner(settings, inst)
        with caplog.at_level("WARNING", logger="federation._inputs"):
            await asyncio.wait_for(runner.run(None), 10)
    cols = "(its columns: time, segment, speed, flow)"
    assert f"{path}: no column 'speeed' {cols}: fields.speeed gives" in caplog.text
    assert f"no column 'segmnt' {cols}: no row can fill label 'seg/{{segmnt}}/flow'" in caplog.text
    assert f"no column 'tme' {cols}: time = 'tme'" in caplog.text
    assert caplog.text.count("no column 'speeed'") == 1  # once, not per row
    warned = [r.getMessage() for r in caplog.records if "no column" in r.getMessage()]
    assert len(warned) == 3 and all(w.count(str(path)) == 1 for w in warned)  # once a line


async def test_a_topic_placeholder_in_a_file_input_s_label_is_a_column_too(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A file has no topic: `{topic}` is filled from a column of that name, or warned."""
    from federation._inputs import FileInput

    path = tmp_path / "loops.csv"
    path.write_text("time,speed\n1,60\n")
    async with DyKnowInstance("t") as inst:
        settings = FileInput(
            kind="file",
            path=path,
            pace="fast",
            time="time",
            create=True,
            fields={"speed": "seg/{topic}/speed"},
            name="loops",
        )
        with caplog.at_level("WARNING", logger="federation._inputs"):
            await asyncio.wait_for(input_runner(settings, inst).run(None), 10)
    line = (
        f"input loops: {path}: no column 'topic' (its columns: time, speed): no row can fill"
        " label 'seg/{topic}/speed' (a file input has no topic)"
    )
    assert line in caplog.text


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("loops.csv", "time,segment,speed\r\n1,s1,60\r\n"),
        ("loops.jsonl", '{"time": 1, "segment": "s1", "speed": 60}\n'),
    ],
    ids=["csv", "jsonl"],
)
async def test_a_file_starting_with_a_byte_order_mark_reads_its_first_column(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, name: str, text: str
) -> None:
    """Excel saves CSV as UTF-8 with a byte-order mark: not part of the first column's name."""
    from federation._inputs import FileInput

    path = tmp_path / name
    path.write_text(text, encoding="utf-8-sig")
    assert path.read_bytes().startswith(b"\xef\xbb\xbf")
    fields = {"speed": "seg/{segment}/speed"}
    async with DyKnowInstance("t") as inst:
        settings = FileInput(
            kind="file", path=path, pace="fast", time="time", create=True, fields=fields
        )
        runner = input_runner(settings, inst)
        with caplog.at_level("WARNING", logger="federation._inputs"):
            await asyncio.wait_for(runner.run(None), 10)
        assert runner.mapper.stats.bad == {} and runner.mapper.stats.samples == 1
        [sample] = inst.latest("seg/s1/speed").samples
        assert (sample.value, sample.valid_time) == (60, 1_000_000_000)
    assert "no column" not in caplog.text


def test_a_payload_that_does_not_decode_is_said_in_the_decoder_s_words() -> None:
    """A malformed MQTT or zenoh payload: where it breaks, not the exception's class."""
    from federation._inputs import BadMessage, MqttInput

    settings = MqttInput(kind="mqtt", topic="traffic/#", fields={"kind": "incident/x"})
    runner = input_runner(settings, DyKnowInstance("t"))
    with pytest.raises(BadMessage) as raised:
        runner.mapper.decode(b'{"segment": "s1", "kind": "acc', "json")
    assert raised.value.reason == "not-json"
    assert raised.value.detail == "Unterminated string starting at: line 1 column 27 (char 26)"


async def test_an_mqtt_input_without_its_broker_names_the_broker(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A wrong broker port: the warning says which broker, and why in words."""
    from agents.transports import free_tcp_port
    from federation._inputs import MqttInput

    port = free_tcp_port()
    settings = MqttInput(kind="mqtt", topic="t/#", port=port, fields={"kind": "incident/x"})
    async with DyKnowInstance("t") as inst:
        inst.add_source("incident/x")
        runner = input_runner(settings, inst)
        with (
            caplog.at_level("WARNING", logger="federation._inputs"),
            contextlib.suppress(TimeoutError),
        ):
            await asyncio.wait_for(runner.run(None), 0.3)
    assert f"input mqtt t/#: MQTT broker 127.0.0.1:{port}: Connection refused;" in caplog.text
    assert "Errno" not in caplog.text


async def test_a_bad_mqtt_message_names_the_topic_it_came_on(
    caplog: pytest.LogCaptureFixture, mosquitto: tuple[str, int]
) -> None:
    """Of many sensors on a wildcard, the warning says which one sent the bad message."""
    import uuid

    import aiomqtt

    from federation._inputs import MqttInput

    host, port = mosquitto
    base = f"trial-{uuid.uuid4().hex[:8]}"  # the broker is the session's: topics of our own
    lidar, long = f"{base}/lidar-3", f"{base}/{'x' * 300}"
    # retained: the input reads them as it subscribes, with no race against its start
    async with aiomqtt.Client(host, port) as client:
        await client.publish(lidar, b'{"kind": "acc', qos=1, retain=True)
        await client.publish(long, b'{"knd": "x"}', qos=1, retain=True)
    settings = MqttInput(
        kind="mqtt", topic=f"{base}/#", host=host, port=port, fields={"kind": "incident/x"}
    )
    try:
        async with DyKnowInstance("t") as inst:
            inst.add_source("incident/x")
            runner = input_runner(settings, inst)
            with caplog.at_level("WARNING", logger="federation._inputs"):
                task = asyncio.create_task(runner.run(None))
                try:
                    async with asyncio.timeout(10):
                        while runner.stats.received < 2:  # noqa: ASYNC110 (no event to await)
                            await asyncio.sleep(0.02)
                finally:
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await task
    finally:
        async with aiomqtt.Client(host, port) as client:  # an empty retained one clears it
            await client.publish(lidar, b"", qos=1, retain=True)
            await client.publish(long, b"", qos=1, retain=True)
    assert f"bad message #1 (not-json) on {lidar}: Unterminated string" in caplog.text
    shown = long[:120] + "…"  # bounded: a topic may be 64 KiB
    assert f"bad message #1 (no-field) on {shown}: none of the fields kind" in caplog.text
    assert "x" * 121 not in caplog.text


@pytest.mark.timeout(60)
async def test_a_zenoh_key_holding_a_newline_forges_no_line_of_a_bad_messages_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # docs/application.md, "Bad messages": the warning names the key a bad message came on;
    # whoever puts on zenoh chooses that key, and a zenoh key may hold a newline or a
    # terminal's escape: written as it is, it forged a log line of the node's
    import zenoh

    from agents.transports import ZenohConfig

    session = zenoh.open(ZenohConfig(mode="peer").to_zenoh())
    try:
        async with DyKnowInstance("t") as inst:
            inst.add_source("lidar/range")
            settings = ZenohInput(kind="zenoh", key="lidar/*", fields={"range": "lidar/range"})
            runner = input_runner(settings, inst)
            with caplog.at_level("WARNING", logger="federation._inputs"):
                task = asyncio.create_task(runner.run(session))
                try:
                    forged = "x\nERROR federation: platform key leaked \x1b[2J"
                    async with asyncio.timeout(10):
                        # put until the input's subscriber is there (it says nothing when)
                        while runner.stats.received < 1:
                            session.put(f"lidar/{forged}", b'{"kind": "acc')
                            await asyncio.sleep(0.05)
                finally:
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await task
    finally:
        session.close()
    [line, *_] = [r.getMessage() for r in caplog.records if "bad message #1" in r.getMessage()]
    assert line.startswith(
        "input zenoh lidar/*: bad message #1 (not-json) on "
        "lidar/x\\x0aERROR federation: platform key leaked \\x1b[2J: "
    ), line
    assert "\n" not in line and "\x1b" not in line
    assert runner.stats.bad["not-json"] == runner.stats.received


async def test_a_time_in_another_unit_is_a_bad_time_not_the_stream_s_latest(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Milliseconds read as seconds put a sample 50 000 years ahead, the latest for ever."""
    from federation._inputs import MqttInput

    settings = MqttInput(kind="mqtt", topic="t/#", time="time", fields={"kind": "incident/s1"})
    async with DyKnowInstance("t") as inst:
        inst.add_source("incident/s1")
        mapper = input_runner(settings, inst).mapper
        now = time.time()
        with caplog.at_level("WARNING", logger="federation._inputs"):
            mapper.handle({"time": int(now * 1000), "kind": "in ms"})
            mapper.handle({"time": now, "kind": "in s"})
        assert mapper.stats.bad == {"bad-time": 1} and mapper.stats.samples == 1
        assert [s.value for s in inst.latest("incident/s1").samples] == ["in s"]
    assert "(bad-time): time is 2.08e+07 days after the message's arrival" in caplog.text
    assert "(time_unit 's': is the time in another unit?)" in caplog.text


async def test_a_time_days_ahead_of_the_clock_is_a_good_time() -> None:
    """A 48 h forecast or a fast simulation is ahead of the wall clock, not in another unit."""
    from federation._inputs import MqttInput

    settings = MqttInput(kind="mqtt", topic="t/#", time="time", fields={"kind": "forecast/s1"})
    async with DyKnowInstance("t") as inst:
        inst.add_source("forecast/s1")
        mapper = input_runner(settings, inst).mapper
        ahead = time.time() + 2 * 86_400
        mapper.handle({"time": ahead, "kind": "in two days"})
        mapper.handle({"time": ahead * 5, "kind": "a fast simulation"})
        assert mapper.stats.bad == {} and mapper.stats.samples == 2
        assert [s.value for s in inst.latest("forecast/s1").samples] == ["a fast simulation"]


@pytest.mark.timeout(120)
def test_an_input_creates_streams_only_for_label_chunks_and_a_bounded_number(
    tmp_path: Path, mosquitto: tuple[str, int]
) -> None:
    # docs/application.md, "create": anyone who can publish to the broker names the objects;
    # a placeholder's value must be one chunk of a label, and an input makes at most
    # `max_streams` streams: past it, a new object's messages are bad ones, the others go on
    import uuid

    host, port = mosquitto
    pub = shutil.which("mosquitto_pub")
    assert pub, "mosquitto-clients is needed (make mosquitto installs it)"
    station = Station(tmp_path, mqtt_port=port)
    base = f"soil-{uuid.uuid4().hex[:8]}"  # the broker is the session's: topics of our own
    with (station.dir / "weather.toml").open("a") as f:
        f.write('"{object}-moisture" = "the soil moisture at a probe, %"\n')
    with (station.dir / "station-labels.toml").open("a") as f:
        f.write('"{object}-moisture" = "soil/{object}/moisture"\n')
    config = (station.dir / "station-mqtt.toml").read_text().split("[[inputs]]")[0]
    (station.dir / "station-soil.toml").write_text(
        config + f'[[inputs]]\nkind = "mqtt"\nhost = "{host}"\nport = {port}\n'
        f'topic = "{base}/+"\ncreate = true\nmax_streams = 2\n'
        'fields = {moisture = "soil/{id}/moisture"}\n'
    )
    messages = [
        {"id": "p1", "moisture": 20},
        {"id": "p 2", "moisture": 1},
        {"id": "", "moisture": 1},
        {"id": "a/b", "moisture": 1},
        {"id": "x" * 300, "moisture": 1},
        {"id": "p2", "moisture": 30},
        {"id": "p3", "moisture": 40},  # a third stream: one more than max_streams
        {"id": "p1", "moisture": 21},  # an object it follows goes on
    ]
    publish = [pub, "-h", host, "-p", str(port), "-t", f"{base}/probes", "-q", "1"]
    try:
        station.start("soil")
        station.follow_stderr()
        # the first retained: read as the input subscribes, whenever that is; once it is
        # in, the input is subscribed and the others come after it, in order
        subprocess.run([*publish, "-r", "-m", json.dumps(messages[0])], check=True, timeout=20)
        station.latest("p1-moisture", until=lambda a: bool(_samples(a, "p1-moisture")))
        subprocess.run(
            [*publish, "-l"],
            input="".join(json.dumps(m) + "\n" for m in messages[1:]),
            text=True,
            check=True,
            timeout=20,
        )
        answer = station.latest(
            "p1-moisture",
            "p2-moisture",
            until=lambda a: [s[0] for s in _samples(a, "p1-moisture")] == [21],
        )
        assert [s[0] for s in _samples(answer, "p2-moisture")] == [30]
        out, err = station.stop()
    finally:
        station.stop()
        subprocess.run([*publish, "-r", "-n"], check=True, timeout=20)  # clears the retained
    [row] = [r for r in _stats(out) if r.get("input") == f"mqtt {base}/+"]
    assert row["received"] == 8 and row["samples"] == 3, row
    assert row["bad"] == {"bad-label-field": 4, "too-many-streams": 1}, row
    chunk = "is not one chunk of a label (1-200 characters, no whitespace, '/', braces or *?[])"
    label = "label 'soil/{id}/moisture'"
    assert f"(bad-label-field) on {base}/probes: {label}: id = 'p 2' {chunk}" in err
    assert f"id = '' {chunk}" in err and f"id = 'a/b' {chunk}" in err
    assert f"id = '{'x' * 40}…' {chunk}" in err and "x" * 41 not in err  # bounded
    assert (
        f"(too-many-streams) on {base}/probes: 'soil/p3/moisture' would be a new stream: "
        "this input has max_streams = 2 of its own already"
    ) in err
    assert "Traceback" not in err


async def test_each_field_of_a_message_counts_on_its_own() -> None:
    # docs/application.md, "fields": a message's fields are used each on its own; one that
    # cannot be (a bad label, no source) costs its own sample only, the message is counted
    # once as bad, and every sample pushed is counted in `samples`
    async with DyKnowInstance("t") as inst:
        inst.add_source("wx/t")
        inst.add_source("car/c1/speed")
        settings = ZenohInput(
            kind="zenoh", key="k", fields={"temp": "wx/t", "speed": "car/{id}/speed"}
        )
        mapper = input_runner(settings, inst).mapper
        mapper.handle({"temp": 20, "id": "c 1", "speed": 3})  # the label's field is bad
        mapper.handle({"temp": 21, "id": "c9", "speed": 4})  # no source car/c9/speed
        mapper.handle({"temp": 22, "id": "c1", "speed": 5})  # both
        mapper.handle({"id": "c1", "speed": 6})  # no temp: the speed alone
        pushed = sum(inst.stream(label).stats()["samples_in"] for label in inst.labels())
        assert pushed == 5
        assert mapper.stats.as_dict() == {
            "input": "zenoh k",
            "received": 4,
            "samples": 5,
            "bad": {"bad-label-field": 1, "no-source": 1},
        }
        assert inst.latest("wx/t").samples[0].value == 22
        assert inst.latest("car/c1/speed").samples[0].value == 6


async def test_a_placeholder_takes_a_string_or_an_integer_only(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # docs/application.md, "fields": a string or an integer makes a label chunk; null is
    # no value (as a missing field), a bool or a float no chunk ("None", "True", "1.0"
    # used to name streams)
    async with DyKnowInstance("t") as inst:
        settings = ZenohInput(kind="zenoh", key="k", fields={"v": "car/{id}/v"}, create=True)
        mapper = input_runner(settings, inst).mapper
        with caplog.at_level("WARNING", logger="federation._inputs"):
            for ident in ("c1", 7, -3, None, True, False, 1.0, 2.5, 10**250):
                mapper.handle({"id": ident, "v": 1})
        assert inst.labels() == ["car/-3/v", "car/7/v", "car/c1/v"]
        assert mapper.stats.samples == 3
        assert mapper.stats.bad == {"no-label-field": 1, "bad-label-field": 5}
        text = caplog.text
        assert "label 'car/{id}/v' needs field 'id' (it is null)" in text
        assert "id = True is a bool, not a string or an integer" in text
        assert "id = 2.5 is a float, not a string or an integer" in text
        assert "id is an integer of over 199 digits: not one chunk of a label" in text


async def test_an_input_goes_on_after_its_stream_is_removed(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # docs/application.md, "create": a stream removed while the input runs (an import
    # that ended, an object a gateway removed) is noticed: without create its messages
    # are `no-source` bad ones until a source is there again, which they then feed; with
    # create the stream is made again, no longer counted in max_streams once removed
    import sys
    import uuid

    from federation._inputs import PythonInput

    module = f"feed_{uuid.uuid4().hex[:8]}"
    (tmp_path / f"{module}.py").write_text(
        "async def messages(queue):\n"
        "    while (item := await queue.get()) is not None:\n"
        "        yield item\n"
        "        queue.task_done()  # the input handled it: it asks for the next\n"
        "    queue.task_done()\n"
    )
    sys.path.insert(0, str(tmp_path))
    try:
        async with DyKnowInstance("t") as inst:
            inst.add_source("wx/t")
            runners, queues, tasks = [], [], []
            for fields, create in (({"t": "wx/t"}, False), ({"v": "car/{id}/v"}, True)):
                queue: asyncio.Queue[Any] = asyncio.Queue()
                settings = PythonInput(
                    kind="python",
                    entry=f"{module}:messages",
                    args={"queue": queue},
                    fields=fields,
                    create=create,
                    max_streams=1,
                )
                runners.append(input_runner(settings, inst))
                queues.append(queue)
                tasks.append(asyncio.create_task(runners[-1].run(None)))

            async def send(n: int, message: dict[str, Any]) -> None:
                queues[n].put_nowait(message)
                await asyncio.wait_for(queues[n].join(), 10)

            await send(0, {"t": 1})
            await send(1, {"id": "c1", "v": 1})
            inst.remove_process("source:wx/t")  # removed: an import that ended
            inst.remove_process("source:car/c1/v")  # an object removed
            with caplog.at_level("WARNING", logger="federation._inputs"):
                await send(0, {"t": 2})
            assert "(no-source): the stream 'wx/t' was removed: no source here until" in (
                caplog.text
            )
            await send(1, {"id": "c1", "v": 2})
            assert inst.labels() == ["car/c1/v"]  # made again: the removed one counts no more
            assert inst.latest("car/c1/v").samples[0].value == 2
            inst.add_source("wx/t")  # the import began again
            await send(0, {"t": 3})
            assert inst.latest("wx/t").samples[0].value == 3
            inst.stream("wx/t").close()  # an import that ended keeping its cache
            with caplog.at_level("WARNING", logger="federation._inputs"):
                await send(0, {"t": 4})
            assert "(no-source): the stream 'wx/t' is closed: its source ended" in caplog.text
            assert [s.value for s in inst.latest("wx/t").samples] == [3]
            assert not any(task.done() for task in tasks)
            assert [r.stats.as_dict() for r in runners] == [
                {"input": ANY, "received": 4, "samples": 2, "bad": {"no-source": 2}},
                {"input": ANY, "received": 2, "samples": 2, "bad": {}},
            ]
            for queue in queues:
                queue.put_nowait(None)
            await asyncio.wait_for(asyncio.gather(*tasks), 10)
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop(module, None)


@pytest.mark.parametrize(
    ("output", "said"),
    [
        (
            {"kind": "mqtt", "topic": "out/+/{label}"},
            "outputs[0].topic: the topic 'out/+/{label}' holds an MQTT wildcard (+ or #), "
            "whatever the label",
        ),
        (
            {"kind": "zenoh", "key": "out/**/{label}"},
            "outputs[0].key: the key 'out/**/{label}' is a zenoh wildcard ($*, *): its put "
            "would reach other keys, whatever the label",
        ),
        (
            {"kind": "zenoh", "key": "out//{label}"},
            "outputs[0].key: the key 'out//{label}' is no zenoh key (Invalid Key Expr "
            "`out//x`: empty chunks are forbidden",
        ),
    ],
)
async def test_an_output_whose_topic_or_key_is_never_plain_stops_the_node_at_start(
    output: dict[str, Any], said: str
) -> None:
    # docs/application.md, "Outputs": the operator's topic or key would refuse every
    # stream; told at start, as a label that is no stream is, not stream by stream
    from types import SimpleNamespace

    from federation._application import NodeApplication
    from federation._outputs import MqttOutput
    from federation._platform import PlatformConfigError

    kind = MqttOutput if output["kind"] == "mqtt" else ZenohOutput
    settings = kind(labels=["wx/t"], **output)
    async with DyKnowInstance("t") as inst:
        inst.add_source("wx/t")
        config = SimpleNamespace(application=None, inputs=[], outputs=[settings])
        platform = SimpleNamespace(instance=inst, config=config, transport=None)
        app = NodeApplication(platform, "t.toml")  # type: ignore[arg-type]
        with pytest.raises(PlatformConfigError) as refused:
            await app.__aenter__()
    assert said in str(refused.value), str(refused.value)


async def test_an_application_stopped_or_refused_lets_go_of_the_instance(tmp_path: Path) -> None:
    # each input follows the instance's label changes (docs/application.md, "create": a
    # stream removed is noticed); the instance may outlive the application (a library's):
    # once it stopped, or was refused at start, nothing of its inputs is kept alive by it
    import sys
    from types import SimpleNamespace

    from federation._application import NodeApplication
    from federation._inputs import PythonInput
    from federation._platform import PlatformConfigError

    module = f"idle_{uuid.uuid4().hex[:8]}"
    (tmp_path / f"{module}.py").write_text(
        "import asyncio\n\nasync def messages():\n    await asyncio.Event().wait()\n    yield {}\n"
    )
    sys.path.insert(0, str(tmp_path))
    try:
        async with DyKnowInstance("t") as inst:
            inst.add_source("wx/t")
            for labels in (["wx/t", "car/{id}/v"], ["wx/t", "wx/nope"]):  # the last refused
                inputs = [
                    PythonInput(
                        kind="python", entry=f"{module}:messages", fields={"t": label}, create=True
                    )
                    if "{" in label
                    else PythonInput(kind="python", entry=f"{module}:messages", fields={"t": label})
                    for label in labels
                ]
                config = SimpleNamespace(application=None, inputs=inputs, outputs=[])
                platform = SimpleNamespace(instance=inst, config=config, transport=None)
                app = NodeApplication(platform, "t.toml")  # type: ignore[arg-type]
                if "wx/nope" in labels:
                    with pytest.raises(PlatformConfigError, match="no source 'wx/nope'"):
                        await app.__aenter__()
                else:
                    async with app:
                        await asyncio.sleep(0)  # the inputs run
                mappers = [weakref.ref(r.mapper) for r in app.inputs]
                assert len(mappers) == 2
                del app, inputs, config, platform
                gc.collect()
                assert [m() for m in mappers] == [None, None]
            inst.remove_process("source:wx/t")  # told to no input left behind
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop(module, None)


async def test_an_application_refused_at_start_is_told_of_no_failure_after(
    tmp_path: Path,
) -> None:
    # its units' failures are said by the application while it runs; refused at start
    # (an input naming no source), it no longer listens to the instance, which may live on
    from types import SimpleNamespace

    from federation._application import NodeApplication
    from federation._inputs import PythonInput
    from federation._platform import PlatformConfigError

    module = f"units_{uuid.uuid4().hex[:8]}"
    (tmp_path / f"{module}.py").write_text("def half(v):\n    return v / 2\n")
    kpl = tmp_path / "app.kpl"
    kpl.write_text(f"source wx/a\ncu half = {module}:half\n    inputs wx/a\n    output wx/b\n")
    try:
        async with DyKnowInstance("t") as inst:
            before = list(inst._failure_listeners)
            spec = PythonInput(kind="python", entry=f"{module}:half", fields={"t": "wx/nope"})
            config = SimpleNamespace(application=kpl, inputs=[spec], outputs=[])
            platform = SimpleNamespace(instance=inst, config=config, transport=None)
            app = NodeApplication(platform, tmp_path / "t.toml")  # type: ignore[arg-type]
            with pytest.raises(PlatformConfigError, match="no source 'wx/nope'"):
                await app.__aenter__()
            assert inst._failure_listeners == before
    finally:
        sys.modules.pop(module, None)


@pytest.mark.timeout(120)
def test_a_created_stream_whose_topic_would_not_be_plain_is_not_published_nor_stops_the_output(
    tmp_path: Path, mosquitto: tuple[str, int]
) -> None:
    # docs/application.md, "Outputs": whoever publishes to an input with create = true names
    # the objects, and a glob output follows their streams at once; a name holding an MQTT
    # wildcard (+, #) or a zenoh one ($) would make the output's publish fail (and stop it
    # for good) or reach other keys' subscribers: such a stream is not published, counted
    # and said, and the output goes on with the others
    import uuid

    host, port = mosquitto
    pub, sub = shutil.which("mosquitto_pub"), shutil.which("mosquitto_sub")
    assert pub and sub, "mosquitto-clients is needed (make mosquitto installs it)"
    station = Station(tmp_path, mqtt_port=port)
    base = f"soil-{uuid.uuid4().hex[:8]}"  # the broker is the session's: topics of our own
    out = f"out-{base}"
    with (station.dir / "weather.toml").open("a") as f:
        f.write('"{object}-moisture" = "the soil moisture at a probe, %"\n')
    with (station.dir / "station-labels.toml").open("a") as f:
        f.write('"{object}-moisture" = "soil/{object}/moisture"\n')
    config = (station.dir / "station-mqtt.toml").read_text().split("[[inputs]]")[0]
    (station.dir / "station-soil.toml").write_text(
        config + f'[[inputs]]\nkind = "mqtt"\nhost = "{host}"\nport = {port}\n'
        f'topic = "{base}/+"\ncreate = true\n'
        'fields = {moisture = "soil/{id}/moisture"}\n'
        f'[[outputs]]\nkind = "mqtt"\nhost = "{host}"\nport = {port}\nretain = true\n'
        f'topic = "{out}/{{label}}"\nlabels = ["soil/*/moisture"]\n'
    )
    messages = [
        {"id": "p1", "moisture": 20},
        {"id": "p#", "moisture": 1},  # its topic would be out-…/soil/p#/moisture
        {"id": "p+", "moisture": 1},
        {"id": "p\u0000", "moisture": 1},  # a NUL is no character of a topic either
        # a control character or a non-character: the broker closes the connection on it
        {"id": "p\u0001", "moisture": 1},
        {"id": "p\u009f", "moisture": 1},
        {"id": "p\ufffe", "moisture": 1},
        {"id": "p\ud800", "moisture": 1},  # a lone surrogate (no UTF-8) makes no label at all
        {"id": "p2", "moisture": 30},
    ]
    publish = [pub, "-h", host, "-p", str(port), "-t", f"{base}/probes", "-q", "1"]
    try:
        station.start("soil")
        station.follow_stderr()
        # the first retained: read as the input subscribes, whenever that is; once it is
        # in, the input is subscribed and the others come after it, in order
        subprocess.run([*publish, "-r", "-m", json.dumps(messages[0])], check=True, timeout=20)
        station.latest("p1-moisture", until=lambda a: bool(_samples(a, "p1-moisture")))
        subprocess.run(
            [*publish, "-l"],
            input="".join(json.dumps(m) + "\n" for m in messages[1:]),
            text=True,
            check=True,
            timeout=20,
        )
        # the output goes on: the stream made after the refused ones is published (retained,
        # so read whenever this subscribes)
        got = subprocess.run(
            [sub, "-h", host, "-p", str(port), "-t", f"{out}/#", "-v", "-C", "2", "-W", "30"],
            capture_output=True,
            text=True,
            timeout=40,
        ).stdout.splitlines()
        stdout, err = station.stop()
        said = {line.split(" ", 1)[0]: json.loads(line.split(" ", 1)[1])["value"] for line in got}
        assert said == {f"{out}/soil/p1/moisture": 20, f"{out}/soil/p2/moisture": 30}, err
    finally:
        station.stop()
        subprocess.run([*publish, "-r", "-n"], check=True, timeout=20)  # clears the retained
        for probe in ("p1", "p2"):
            topic = f"{out}/soil/{probe}/moisture"
            subprocess.run([pub, "-h", host, "-p", str(port), "-t", topic, "-r", "-n"], timeout=20)
    [row] = [r for r in _stats(stdout) if r.get("output") == f"mqtt {out}/{{label}}"]
    assert row == {"output": f"mqtt {out}/{{label}}", "published": 2, "dropped": 0, "refused": 6}
    for shown, why in (
        ("p#", "holds an MQTT wildcard (+ or #)"),
        ("p+", "holds an MQTT wildcard (+ or #)"),
        ("p\\x00", "holds a NUL character"),
        ("p\\x01", "holds a control character or a Unicode non-character"),
    ):
        assert (
            f"output mqtt {out}/{{label}}: stream 'soil/{shown}/moisture' not published: "
            f"its topic '{out}/soil/{shown}/moisture' {why}"
        ) in err, err
    [row] = [r for r in _stats(stdout) if r.get("input") == f"mqtt {base}/+"]
    assert row["received"] == 9 and row["bad"] == {"bad-label-field": 1}, row
    assert "id = 'p\\ud800' is not one chunk of a label" in err, err
    assert "stopped" not in err and "Traceback" not in err
    assert "reconnecting" not in err, err  # the broker never closed the output's connection
