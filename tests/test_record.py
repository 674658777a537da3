"""Recordings: MCAP files, Recorder, replay on a manual clock, dyknow record / replay."""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import io
import json
import os
import re
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path
from typing import Any

import msgpack
import orjson
import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.writer import Writer as McapWriter

from dyknow_core import (
    NS_PER_S,
    ChangeEvent,
    DyKnowInstance,
    ManualClock,
    RealClock,
    Recorder,
    RecordError,
    Recording,
    RecordWriter,
    UnknownLabelError,
    advance_to,
    kpl,
    read_recording,
    replay,
    sample_json,
)
from dyknow_core._record import DKR_MAGIC, settle
from federation.cli import main
from tests.test_cli import PRODUCER, ROOT, _free_port, _kill, _write_federation

MS = NS_PER_S // 1000

# a CU, a change-event stream, a state-based monitor and a chronicle over the changes
SPEC = """
source car/speed
source car/offset
cu road = examples.kpl_functions:on_road
    inputs car/offset
    output car/on_road
monitor speeding = "always[0,2](speed < 30)" every 1
    with {speed: car/speed}
changes car/on_road
chronicle left_road {
    input on_road = events/changed/car/on_road
    event leave = on_road from true to false
    event back = on_road from false to true
    constraint leave -> back in [0, 30]
}
"""
SOURCES = ["car/offset", "car/speed"]


def _samples(path: Path) -> list[tuple[str, Any, int, int]]:
    return [tuple(s) for s in read_recording(path)]  # type: ignore[misc]


def _derived(inst: DyKnowInstance) -> dict[str, list[tuple[Any, int, int]]]:
    return {
        label: [tuple(s) for s in inst.between(label, -(2**62), 2**62, all_estimates=True).samples]
        for label in inst.labels()
        if label not in SOURCES
    }


# -- the file format ------------------------------------------------------------------------------


async def test_round_trip_keeps_values_times_labels_and_order(tmp_path: Path) -> None:
    path = tmp_path / "flight.mcap"
    clock = ManualClock(5 * NS_PER_S)
    values: list[Any] = [1, 2.5, "text", {"x": [1, 2], "y": None}, [1, "a", None], None, True]
    async with DyKnowInstance("uav-a", clock=clock) as inst:
        gps, cam = inst.add_source("gps/pos"), inst.add_source("camera/objects")
        async with Recorder(inst, ["gps/pos", "camera/objects"], path) as rec:
            expected = []
            for k, value in enumerate(values):
                ta = clock.now() + (k + 1) * 10 * MS
                src, label = (gps, "gps/pos") if k % 2 == 0 else (cam, "camera/objects")
                src.push(value, ta - 7 * MS, ta)  # valid time 7 ms before available
                expected.append((label, value, ta - 7 * MS, ta))
            # a tuple travels as a list; the core's value types come back as themselves
            gps.push(ChangeEvent(old=(1, 2), new=3), ta + 1, ta + 2)
            expected.append(("gps/pos", ChangeEvent(old=[1, 2], new=3), ta + 1, ta + 2))
            assert rec.counts == {"gps/pos": 5, "camera/objects": 3}
    got = _samples(path)
    assert got == expected
    assert isinstance(got[-1][1], ChangeEvent)
    header = read_recording(path).header
    assert (header.version, header.instance, header.clock) == (2, "uav-a", "ManualClock")
    assert header.start == 5 * NS_PER_S and header.labels == ["gps/pos", "camera/objects"]
    assert (header.format, header.time_offset) == ("mcap", 10**18)  # not an epoch clock


async def test_every_stream_including_those_created_after_the_start(tmp_path: Path) -> None:
    path = tmp_path / "all.mcap"
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as inst:
        a = inst.add_source("a")
        async with Recorder(inst, None, path):
            a.push(1, 0, 1)
            late = inst.add_source("late")  # created after the recorder started
            late.push("first", 1, 2)  # published before anyone could subscribe to it
            a.push(2, 2, 3)
            late.push("second", 3, 4)
            await settle()
    assert _samples(path) == [
        ("a", 1, 0, 1),
        ("late", "first", 1, 2),
        ("a", 2, 2, 3),
        ("late", "second", 3, 4),
    ]
    assert read_recording(path).header.labels is None


def test_an_unknown_label_is_refused_before_a_file_is_made(tmp_path: Path) -> None:
    with pytest.raises(UnknownLabelError, match="nope"):
        Recorder(DyKnowInstance(clock=ManualClock()), ["nope"], tmp_path / "x.mcap").start()
    assert not (tmp_path / "x.mcap").exists()
    with pytest.raises(RecordError, match="cannot be written"):
        RecordWriter(tmp_path / "missing" / "x.mcap")


async def test_batches_are_written_while_recording(tmp_path: Path) -> None:
    path = tmp_path / "batches.mcap"
    async with DyKnowInstance(clock=ManualClock()) as inst:
        src = inst.add_source("x")
        async with Recorder(inst, ["x"], path, batch_size=4, flush_interval=0.05) as rec:
            for k in range(10):
                src.push(k, k, k + 1)
            # full batches are on disk at once: memory holds less than a batch
            assert [s[1] for s in read_recording(path)] == list(range(8))
            assert rec.writer is not None and len(rec.writer._pending) == 2
            # the rest is flushed within the flush interval, the recorder still running
            for _ in range(500):  # at most 5 s
                if len(_samples(path)) == 10:
                    break
                await asyncio.sleep(0.01)
            assert len(_samples(path)) == 10


def test_a_truncated_file_reads_up_to_its_last_complete_batch(tmp_path: Path) -> None:
    path = tmp_path / "cut.mcap"
    w = RecordWriter(path, instance="i", batch_size=3)
    for k in range(7):
        w.add("x", k, k, k)
    complete = path.stat().st_size  # two batches of 3 are written, each a chunk
    assert [s[1] for s in read_recording(path)] == [0, 1, 2, 3, 4, 5]  # while it writes
    w.close()
    data = path.read_bytes()
    for cut in (complete + 3, complete + 20):  # mid record header, mid chunk
        path.write_bytes(data[:cut])
        rec = read_recording(path)
        assert [s[1] for s in rec] == [0, 1, 2, 3, 4, 5]
        assert rec.truncated and rec.info()["truncated"]
    path.write_bytes(data[:-1])  # every chunk, the summary cut: read in file order
    rec = read_recording(path)
    assert [s[1] for s in rec] == list(range(7)) and rec.truncated
    path.write_bytes(data)
    rec = read_recording(path)
    assert [s[1] for s in rec] == list(range(7)) and not rec.truncated


def _frame(obj: Any) -> bytes:
    payload = msgpack.packb(obj)
    return struct.pack(">II", len(payload), zlib.crc32(payload)) + payload


def _mcap_with(metadata: dict[str, str]) -> bytes:
    out = io.BytesIO()
    w = McapWriter(out)
    w.start()
    w.add_metadata("dyknow", metadata)
    w.finish()
    return out.getvalue()


MCAP_MAGIC = b"\x89MCAP0\r\n"


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (None, "no such file"),
        ("dir", "is a directory"),
        (b"hello world, not a recording", "not a recording"),
        (MCAP_MAGIC + b"\x01\x02", "corrupt header"),
        (_mcap_with({"format": "dyknow-record", "version": "9"}), "format version 9"),
        (_mcap_with({"format": "other"}), "corrupt header"),
        (DKR_MAGIC + b"\x00\x00\x00\x05\x00\x00\x00\x00abcde", "corrupt header"),
        (DKR_MAGIC + b"\x00\x00", "corrupt header"),
        (DKR_MAGIC + _frame({"format": "dyknow-record", "version": 7}), "format version 7"),
        (DKR_MAGIC + _frame({"format": "something-else", "version": 1}), "corrupt header"),
    ],
)
def test_bad_files_are_refused_naming_the_file_and_the_problem(
    tmp_path: Path, content: Any, problem: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bad.mcap"
    if content == "dir":
        path.mkdir()
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(RecordError, match=problem) as err:
        read_recording(path)
    assert str(path) in str(err.value)
    for args in (["replay", str(path)], ["replay", "--info", str(path)]):
        assert main(args) == 2
        out = capsys.readouterr()
        assert str(path) in out.err and problem in out.err and "Traceback" not in out.err


def test_a_corrupt_chunk_is_an_error_after_the_good_ones(tmp_path: Path) -> None:
    path = tmp_path / "flip.mcap"
    w = RecordWriter(path, batch_size=2)
    for k in range(4):
        w.add("x", k, k, k)
    w.close()
    with path.open("rb") as f:
        second = make_reader(f).get_summary().chunk_indexes[1]  # type: ignore[union-attr]
    data = bytearray(path.read_bytes())
    data[second.chunk_start_offset + second.chunk_length - 3] ^= 0xFF  # its compressed data
    path.write_bytes(bytes(data))
    got = []
    # the message names where the damaged chunk starts, as `mcap` lists it
    where = rf"flip.mcap: corrupt chunk at byte {second.chunk_start_offset}: "
    with pytest.raises(RecordError, match=where):
        for s in read_recording(path):
            got.append(s.value)
    assert got == [0, 1]
    proc = subprocess.run(
        [sys.executable, "-m", "federation.cli", "replay", str(path)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    assert re.search(where, proc.stderr) and "Traceback" not in proc.stderr


def test_a_corrupt_chunk_without_a_chunk_index_is_named_by_its_start(tmp_path: Path) -> None:
    # a killed writer's file has no index: the chunk is found by the records' framing
    path = tmp_path / "killed.mcap"
    w = RecordWriter(path, batch_size=2)
    for k in range(6):
        w.add("x", k, k, k)
    w.close()
    with path.open("rb") as f:
        second = make_reader(f).get_summary().chunk_indexes[1]  # type: ignore[union-attr]
    data = bytearray(path.read_bytes()[:-20])  # no footer: as if the writer was killed
    data[second.chunk_start_offset + second.chunk_length - 3] ^= 0xFF
    path.write_bytes(bytes(data))
    got = []
    where = rf"killed.mcap: corrupt chunk at byte {second.chunk_start_offset}: "
    with pytest.raises(RecordError, match=where):
        for s in read_recording(path):
            got.append(s.value)
    assert got == [0, 1]


def test_values_round_trip_through_json(tmp_path: Path) -> None:
    path = tmp_path / "values.mcap"
    values: list[Any] = [
        float("nan"),
        float("inf"),
        -0.5,
        2**70,
        b"\x00\xffraw",
        {1: "int key", (1, 2): "tuple key"},
        {"nested": [ChangeEvent(old=None, new=b"x")]},
        {"$type": "ChangeEvent", "old": 1, "new": 2},  # a dict naming a type: rebuilt
        (1, "tuple"),
        {"a", "set"} - {"set"},
        object(),  # recorded as its repr, counted
    ]
    w = RecordWriter(path)
    for k, v in enumerate(values):
        w.add("v", v, k, k)
    w.close()
    assert w.unencodable == 1
    got = [s.value for s in read_recording(path)]
    assert str(got[0]) == "nan" and got[1:4] == [float("inf"), -0.5, 2**70]
    assert got[4:7] == [b"\x00\xffraw", {1: "int key", (1, 2): "tuple key"}, values[6]]
    assert got[7] == ChangeEvent(1, 2) and got[8] == [1, "tuple"] and got[9] == ["a"]
    assert got[10].startswith("<object object at")


def test_a_dkr_file_of_version_1_is_still_read(tmp_path: Path) -> None:
    path = tmp_path / "old.dkr"
    header = {"format": "dyknow-record", "version": 1, "instance": "old", "clock": "ManualClock"}
    header |= {"start": 0, "labels": ["x", "y"], "created": "2026-01-01T00:00:00+00:00"}
    typed = msgpack.ExtType(1, msgpack.packb(["ChangeEvent", {"old": 1, "new": 2}]))
    batch = {"l": ["x", "y"], "s": [[0, 1.5, -3, 1], [1, typed, 2, 3], [0, [1, 2], 3, 4]]}
    path.write_bytes(DKR_MAGIC + _frame(header) + _frame(batch) + _frame(batch)[:5])
    rec = read_recording(path)
    assert (rec.header.format, rec.header.version, rec.header.instance) == ("dkr", 1, "old")
    assert _samples(path) == [
        ("x", 1.5, -3, 1),
        ("y", ChangeEvent(1, 2), 2, 3),
        ("x", [1, 2], 3, 4),
    ]
    assert rec.info()["truncated"]


# -- MCAP as other tools see it ------------------------------------------------------------------


def _time(t: dict[str, int]) -> int:
    return t["sec"] * NS_PER_S + t["nsec"]


@pytest.mark.parametrize("start", [0, 1_764_000_000 * NS_PER_S])
async def test_the_mcap_library_finds_every_sample(tmp_path: Path, start: int) -> None:
    """Our recording read by mcap's own reader: labels as channels, values, both times."""
    path = tmp_path / "flight.mcap"
    clock = ManualClock(start)
    expected: list[tuple[str, Any, int, int]] = []
    async with DyKnowInstance("uav-a", clock=clock) as inst:
        alt, pos = inst.add_source("uav/altitude"), inst.add_source("uav/position")
        async with Recorder(inst, ["uav/altitude", "uav/position"], path, batch_size=4):
            for k in range(10):
                ta = start + k * 100 * MS
                tv = ta - 250 * MS  # valid before available: negative at a clock's 0
                alt.push(100.0 + k, tv, ta)
                pos.push({"lat": 58.0 + k, "lon": 15.0}, tv, ta + 1)
                expected += [("uav/altitude", 100.0 + k, tv, ta)]
                expected += [("uav/position", {"lat": 58.0 + k, "lon": 15.0}, tv, ta + 1)]
    offset = 0 if start else 10**18  # an epoch clock as it is, another shifted
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 20 and len(summary.chunk_indexes) == 5
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == {"uav/altitude", "uav/position"}
        for channel in channels.values():
            assert channel.message_encoding == "json"
            schema = summary.schemas[channel.schema_id]
            assert (schema.name, schema.encoding) == (channel.topic, "jsonschema")
            properties = json.loads(schema.data)["properties"]
            assert {"valid_time", "available_time"} <= set(properties)
        assert json.loads(summary.schemas[channels["uav/altitude"].schema_id].data)["properties"][
            "value"
        ] == {"type": "number"}
        (meta,) = reader.iter_metadata()
        assert meta.name == "dyknow" and meta.metadata["time_offset"] == str(offset)
        assert meta.metadata["instance"] == "uav-a" and meta.metadata["version"] == "2"
        # every field the format promises, as an outside tool reads them
        md = meta.metadata
        assert (md["format"], md["clock"], md["start"]) == (
            "dyknow-record",
            "ManualClock",
            str(start),
        )
        assert json.loads(md["labels"]) == ["uav/altitude", "uav/position"]
        assert json.loads(md["meta"]) == {} and md["time_unit"] == "ns"
        created = datetime.datetime.fromisoformat(md["created"])
        assert created.utcoffset() == datetime.timedelta(0)
        header = reader.get_header()
        assert header.profile == "" and header.library.startswith("dyknow; mcap-python/")
        got = []
        for _, channel, message in reader.iter_messages(log_time_order=True):
            body = orjson.loads(message.data)
            tv, ta = _time(body["valid_time"]), _time(body["available_time"])
            assert (message.log_time, message.publish_time) == (ta + offset, tv + offset)
            assert message.data == sample_json(body["value"], tv, ta)
            got.append((channel.topic, body["value"], tv, ta))
    assert got == expected
    assert _samples(path) == expected  # and ours reads the same
    with path.open("rb") as f:  # the metadata comes before any message
        kinds = [type(r).__name__ for r in StreamReader(f).records]
    assert kinds.index("Metadata") < kinds.index("Message")


def test_replay_of_an_mcap_file_written_by_the_mcap_library(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A foreign JSON MCAP file: topics are labels (no leading '/'), publish time valid, log
    time available."""
    path = tmp_path / "foreign.mcap"
    t0 = 1_764_000_000 * NS_PER_S
    with path.open("wb") as f:
        w = McapWriter(f)
        w.start(profile="", library="someone else")
        schema = w.register_schema("Reading", "jsonschema", b'{"type": "object"}')
        temp = w.register_channel("/station/temp", "json", schema)
        wind = w.register_channel("/station/wind", "json", schema)
        raw = w.register_channel("/camera/raw", "protobuf", 0)
        # written out of log-time order across channels; a publish time of 0 means "none"
        w.add_message(temp, t0 + 30 * MS, b'{"c": 20.5}', t0 + 10 * MS)
        w.add_message(wind, t0 + 20 * MS, b'{"ms": 3}', 0)
        w.add_message(raw, t0 + 25 * MS, b"\x08\x01", t0)
        w.add_message(temp, t0 + 60 * MS, b'{"c": 21.0}', t0 + 40 * MS)
        w.finish()
    assert main(["replay", str(path), "--json"]) == 0
    out = capsys.readouterr()
    rows = [json.loads(line) for line in out.out.splitlines()]
    summary = rows.pop()["summary"]
    assert [(r["label"], r["value"], r["valid"], r["available"]) for r in rows] == [
        ("station/wind", {"ms": 3}, t0 + 20 * MS, t0 + 20 * MS),
        ("station/temp", {"c": 20.5}, t0 + 10 * MS, t0 + 30 * MS),
        ("station/temp", {"c": 21.0}, t0 + 40 * MS, t0 + 60 * MS),
    ]
    assert summary["counts"] == {"station/temp": 2, "station/wind": 1}
    assert summary["undecodable"] == {"camera/raw": 1}
    assert "camera/raw: 1 messages not decoded" in out.err and "protobuf" in out.err
    assert main(["replay", "--info", str(path)]) == 0
    text = capsys.readouterr().out
    assert "written by someone else" in text and "station/temp: 2" in text
    # its writer killed (no summary, no index): still in log-time order
    path.write_bytes(path.read_bytes()[:-30])
    rec = read_recording(path)
    assert [(s.label, s.available_time) for s in rec] == [
        ("station/wind", t0 + 20 * MS),
        ("station/temp", t0 + 30 * MS),
        ("station/temp", t0 + 60 * MS),
    ]
    assert rec.truncated


def _ros_messages() -> list[tuple[str, str, Any, int]]:
    """(topic, ROS type, message, bag time) of a short ROS 2 flight, in time order."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    pose, float64 = (
        store.types["geometry_msgs/msg/PoseStamped"],
        store.types["std_msgs/msg/Float64"],
    )
    header, stamp = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    point, quat = (
        store.types["geometry_msgs/msg/Point"],
        store.types["geometry_msgs/msg/Quaternion"],
    )
    posecls = store.types["geometry_msgs/msg/Pose"]
    t0 = 1_764_000_000 * NS_PER_S
    out = []
    for n in range(3):
        t = t0 + n * 100 * MS
        sec, nsec = divmod(t - 30 * MS, NS_PER_S)  # stamped 30 ms before it was logged
        msg = pose(
            header(stamp(sec, nsec), "map"),
            posecls(point(float(n), 2.0, 3.0), quat(0.0, 0.0, 0.0, 1.0)),
        )
        out.append(("/uav/pose", "geometry_msgs/msg/PoseStamped", msg, t))
        out.append(("/uav/temp", "std_msgs/msg/Float64", float64(20.0 + n), t + 5 * MS))
    return out


def _expected_ros_rows() -> list[tuple[str, Any, int, int]]:
    """What a replay gives of ``_ros_messages``: labels without the topics' leading '/'."""
    rows = []
    for topic, _, msg, t in _ros_messages():
        if topic == "/uav/pose":
            value = {"x": msg.pose.position.x, "frame": "map"}
            rows.append(("uav/pose", value, t - 30 * MS, t))
        else:
            rows.append(("uav/temp", {"data": msg.data}, t, t))
    return rows


def _ros_rows(out: str) -> list[tuple[str, Any, int, int]]:
    rows = [json.loads(line) for line in out.splitlines()][:-1]
    got = []
    for r in rows:
        v = r["value"]
        if r["label"] == "uav/pose":
            v = {"x": v["pose"]["position"]["x"], "frame": v["header"]["frame_id"]}
        got.append((r["label"], v, r["valid"], r["available"]))
    return got


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_replay_of_a_rosbag2_bag_written_by_rosbags(
    tmp_path: Path, storage: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """A rosbag2 bag: topics are labels, header.stamp valid (else bag time), bag time available."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    bag = tmp_path / "flight_bag"
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(bag, version=9, storage_plugin=plugin) as w:
        conns: dict[str, Any] = {}
        for topic, rostype, msg, t in _ros_messages():
            if topic not in conns:
                conns[topic] = w.add_connection(topic, rostype, typestore=store)
            w.write(conns[topic], t, bytes(store.serialize_cdr(msg, rostype)))
    assert main(["replay", str(bag), "--json"]) == 0
    assert _ros_rows(capsys.readouterr().out) == _expected_ros_rows()
    assert main(["replay", "--info", str(bag)]) == 0
    assert "rosbag2" in capsys.readouterr().out


def test_a_damaged_rosbag2_bag_is_named_not_a_crash(tmp_path: Path) -> None:
    """A bag whose database holds a time stamp that is no integer: exit 2 naming the bag."""
    import sqlite3

    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    bag = tmp_path / "damaged_bag"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        conns: dict[str, Any] = {}
        for topic, rostype, msg, t in _ros_messages():
            if topic not in conns:
                conns[topic] = w.add_connection(topic, rostype, typestore=store)
            w.write(conns[topic], t, bytes(store.serialize_cdr(msg, rostype)))
    (db,) = bag.glob("*.db3")
    with contextlib.closing(sqlite3.connect(db)) as con, con:
        con.execute("UPDATE messages SET timestamp = X'00' WHERE id = 2")  # a blob
    for args in (["--info", str(bag)], [str(bag)]):  # a process of its own, as a user runs it
        r = subprocess.run(
            [sys.executable, "-m", "federation.cli", "replay", *args],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=60,
        )
        assert r.returncode == 2, (r.returncode, r.stderr)
        assert f"{bag}: damaged rosbag2 bag: a time stamp is bytes" in r.stderr, r.stderr
        assert "Traceback" not in r.stderr


def test_replay_of_a_ros2_mcap_file_written_by_the_mcap_library(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """ROS 2 messages (CDR) in an MCAP file of the mcap library: decoded, stamped, in order."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    path = tmp_path / "ros.mcap"
    with path.open("wb") as f:
        w = McapWriter(f)
        w.start(profile="ros2", library="a ROS tool")
        channels: dict[str, int] = {}
        for n, (topic, rostype, msg, t) in enumerate(_ros_messages()):
            if topic not in channels:
                msgdef, _ = store.generate_msgdef(rostype)
                schema = w.register_schema(rostype, "ros2msg", msgdef.encode())
                channels[topic] = w.register_channel(topic, "cdr", schema)
            w.add_message(channels[topic], t, bytes(store.serialize_cdr(msg, rostype)), t, n)
        w.finish()
    assert main(["replay", str(path), "--json"]) == 0
    assert _ros_rows(capsys.readouterr().out) == _expected_ros_rows()


# -- replay ---------------------------------------------------------------------------------------


async def _live_run(path: Path) -> dict[str, list[tuple[Any, int, int]]]:
    """A live run on a manual clock with the spec, every stream recorded; its outputs."""
    clock = ManualClock()
    async with DyKnowInstance("live", clock=clock) as inst:
        kpl.setup(inst, SPEC)
        speed, offset = inst.processes["source:car/speed"], inst.processes["source:car/offset"]
        async with Recorder(inst, None, path):
            for k in range(40):
                t = k * NS_PER_S // 4
                await advance_to(clock, t)
                # the car leaves the road for a while, twice; it speeds up past 30
                off = 8.0 if 10 <= k < 14 or 25 <= k < 28 else 1.0
                speed.push(20.0 + k / 2, t - 30 * MS, t)  # type: ignore[attr-defined]
                offset.push(off, t - 50 * MS, t + MS)  # type: ignore[attr-defined]
                await settle()
            await advance_to(clock, 11 * NS_PER_S)
        return _derived(inst)


async def _replay(path: Path) -> dict[str, list[tuple[Any, int, int]]]:
    """The recording's sources replayed through the same spec; its outputs."""
    rec = read_recording(path)
    async with DyKnowInstance("replay", clock=ManualClock(rec.header.start)) as inst:
        kpl.setup(inst, SPEC)
        summary = await replay(path, inst, labels=SOURCES, tail=1.25)
        assert summary.counts == {"car/speed": 40, "car/offset": 40}
        assert set(summary.skipped) == {
            "car/on_road",
            "events/changed/car/on_road",
            "monitors/speeding",
            "monitors/speeding/state",
            "chronicles/left_road",
        }
        assert summary.valid_span == (-50 * MS, 39 * NS_PER_S // 4 - 30 * MS)
        return _derived(inst)


async def test_replay_is_deterministic_and_reproduces_the_live_run(tmp_path: Path) -> None:
    path = tmp_path / "live.mcap"
    live = await _live_run(path)
    assert len(live["chronicles/left_road"]) == 3  # the scenario does recognize something
    assert any(not s[0]["verdict"] for s in live["monitors/speeding"])
    first, second = await _replay(path), await _replay(path)
    assert first == second
    assert first == live
    # what was recorded of the derived streams is what the replay recomputed
    recorded: dict[str, list[tuple[Any, int, int]]] = {}
    for s in read_recording(path):
        if s.label not in SOURCES:
            recorded.setdefault(s.label, []).append((s.value, s.valid_time, s.available_time))
    assert recorded == {k: v for k, v in live.items() if v}


async def test_replay_paces_at_the_given_speed(tmp_path: Path) -> None:
    path = tmp_path / "paced.mcap"
    w = RecordWriter(path)
    for k in range(5):
        w.add("x", k, k * NS_PER_S // 10, k * NS_PER_S // 10)  # 0.4 s of recording
    w.close()
    async with DyKnowInstance(clock=ManualClock()) as inst:
        began = time.monotonic()
        await replay(path, inst, speed=2.0)
        assert time.monotonic() - began >= 0.19  # 0.4 s at twice the speed
        assert [s.value for s in inst.between("x", 0, NS_PER_S).samples] == list(range(5))


async def test_replay_needs_a_manual_clock_and_a_free_label(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    w = RecordWriter(path)
    w.add("x", 1, 0, 0)
    w.close()
    with pytest.raises(TypeError, match="ManualClock"):
        await replay(path, DyKnowInstance(clock=RealClock()))
    inst = DyKnowInstance(clock=ManualClock())
    inst.add_source("y")
    inst.add_cu("copy", lambda v: v, ["y"], "x")
    with pytest.raises(RecordError, match=r"'x' is published .* by something other than a source"):
        await replay(path, inst)
    with pytest.raises(ValueError, match="speed"):
        await replay(path, DyKnowInstance(clock=ManualClock()), speed=0)


# -- the CLI --------------------------------------------------------------------------------------


def test_cli_replay_info_and_kpl_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "live.mcap"
    live = asyncio.run(_live_run(path))
    spec = tmp_path / "app.kpl"
    spec.write_text(SPEC)

    assert main(["replay", "--info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["counts"]["car/speed"] == 40 and info["instance"] == "live"
    assert info["version"] == 2 and not info["truncated"]
    assert main(["replay", "--info", str(path)]) == 0
    text = capsys.readouterr().out
    assert "car/offset: 40" in text and "MCAP, dyknow-record version 2" in text

    args = ["replay", str(path), "--kpl", str(spec), "--json", "--tail", "1.25"]
    outputs = []
    for _ in range(2):
        assert main(args) == 0
        outputs.append(capsys.readouterr().out)
    assert outputs[0] == outputs[1]  # deterministic, byte for byte
    lines = [json.loads(line) for line in outputs[0].splitlines()]
    summary = lines.pop()["summary"]
    assert summary["counts"] == {"car/offset": 40, "car/speed": 40}
    assert summary["not_fed"]["chronicles/left_road"] == 3 and summary["failures"] == []
    chron = [r for r in lines if r["label"] == "chronicles/left_road"]
    assert [(r["valid"], r["available"]) for r in chron] == [
        (tv, ta) for _, tv, ta in live["chronicles/left_road"]
    ]
    assert chron[0]["value"]["chronicle"] == "left_road"

    # --print picks the streams; text output names each with its valid time
    assert main(["replay", str(path), "--kpl", str(spec), "--print", "monitors/speeding"]) == 0
    text = capsys.readouterr().out
    assert "monitors/speeding  valid=" in text and "chronicles/" not in text.split("replayed")[0]
    assert "replayed 80 samples" in text
    # an unknown --print label, a bad spec: exit 2, named
    assert main(["replay", str(path), "--kpl", str(spec), "--print", "nowhere"]) == 2
    assert "'nowhere'" in capsys.readouterr().err
    assert main(["replay", str(path), "--speed", "0"]) == 2
    assert "--speed must be > 0" in capsys.readouterr().err
    assert main(["replay", str(path), "--kpl", str(tmp_path / "none.kpl")]) == 2
    assert "none.kpl: cannot read" in capsys.readouterr().err
    bad = tmp_path / "bad.kpl"
    bad.write_text("cu c = examples.kpl_functions:on_road inputs missing/label output o\n")
    assert main(["replay", str(path), "--kpl", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}:1:" in err and "missing/label" in err and "Traceback" not in err
    # a CU that checks but does not import: FILE:LINE:COL as check's errors are
    bad.write_text("source car5/speed\ncu c = nowhere_module:f inputs car5/speed output o\n")
    assert main(["replay", str(path), "--kpl", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}:2:1: cu 'c': " in err and "nowhere_module" in err and "Traceback" not in err


def test_cli_help_explains_record_and_replay(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["record", "--help"]) == 0
    text = capsys.readouterr().out
    assert "--out" in text and "--duration" in text and "--count" in text
    assert main(["replay", "--help"]) == 0
    text = capsys.readouterr().out
    assert "--kpl" in text and "--print" in text and "--speed" in text and "--info" in text


@pytest.mark.timeout(90)
def test_record_from_a_federation_then_replay(tmp_path: Path) -> None:
    configs = _write_federation(tmp_path, _free_port())
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    producer = subprocess.Popen(
        [sys.executable, "-c", PRODUCER, str(configs["uav-a"])],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        cwd=ROOT,
        env=env,
    )
    cli = [sys.executable, "-m", "federation.cli"]
    op = ["--config", str(configs["operator"]), "--platform", "uav-a"]
    recorder: subprocess.Popen[str] | None = None
    try:
        assert producer.stdout is not None
        assert producer.stdout.readline().strip() == "ready"
        # --count: stops by itself after 3 samples
        counted = tmp_path / "counted.mcap"
        done = subprocess.run(
            [*cli, "record", "heli-altitude", *op, "--out", str(counted), "--count", "3"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env=env,
            timeout=30,
        )
        assert done.returncode == 0, done.stderr
        assert "3 samples (heli-altitude=3) written to" in done.stdout
        got = _samples(counted)
        assert [s[0] for s in got] == ["heli-altitude"] * 3
        values = [s[1] for s in got]
        assert values == sorted(values) and values[0] >= 100.0
        header = read_recording(counted).header
        assert header.labels == ["heli-altitude"] and header.meta["platform"] == "uav-a"

        # no limit: SIGTERM ends it cleanly, the file complete
        signalled = tmp_path / "signalled.mcap"
        recorder = subprocess.Popen(
            [*cli, "record", "heli-altitude", *op, "--out", str(signalled)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env=env,
        )
        assert recorder.stderr is not None
        for line in recorder.stderr:  # bounded by the test's timeout
            if line.startswith("recording ") and " 0 samples" not in line:
                break
        recorder.send_signal(signal.SIGTERM)
        out, err = recorder.communicate(timeout=15)
        assert recorder.returncode == 0, err
        assert "written to" in out and "Traceback" not in err
        rec = Recording(signalled)
        assert len(list(rec)) >= 1 and not rec.truncated

        # and back through a local instance
        replayed = subprocess.run(
            [*cli, "replay", str(counted), "--json"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env=env,
            timeout=30,
        )
        assert replayed.returncode == 0, replayed.stderr
        rows = [json.loads(line) for line in replayed.stdout.splitlines()]
        assert [r["value"] for r in rows[:-1]] == values
        assert rows[-1]["summary"]["counts"] == {"heli-altitude": 3}
    finally:
        if recorder is not None:
            _kill(recorder)
        _kill(producer)


def _ros_mcap(path: Path) -> None:
    """``_ros_messages`` in an MCAP file, as a ROS tool writes it."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    with path.open("wb") as f:
        w = McapWriter(f)
        w.start(profile="ros2", library="a ROS tool")
        channels: dict[str, int] = {}
        for n, (topic, rostype, msg, t) in enumerate(_ros_messages()):
            if topic not in channels:
                msgdef, _ = store.generate_msgdef(rostype)
                schema = w.register_schema(rostype, "ros2msg", msgdef.encode())
                channels[topic] = w.register_channel(topic, "cdr", schema)
            w.add_message(channels[topic], t, bytes(store.serialize_cdr(msg, rostype)), t, n)
        w.finish()


def test_a_monitor_comparing_a_whole_message_with_a_number_says_so(tmp_path: Path) -> None:
    """``temp > 20`` on a Float64 topic is never true: a warning names the fields to read.

    Before, every state was a violation and nothing was said. A nested field is read
    with a dotted path: ``pose("pose.position.x")``.
    """
    path = tmp_path / "ros.mcap"
    _ros_mcap(path)
    spec = tmp_path / "app.kpl"
    spec.write_text(
        "source uav/temp\nsource uav/pose\n"
        'monitor warm = "always (temp > 20)" every 0.1\n    with {temp: uav/temp}\n'
        'monitor east = "always not (pose(\\"pose.position.x\\") >= 0)" every 0.1\n'
        "    with {pose: uav/pose}\n"
    )
    r = subprocess.run(
        [
            *(sys.executable, "-m", "federation.cli", "replay", str(path)),
            *("--kpl", str(spec), "--json", "--tail", "0.2"),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert (
        "monitor monitors/warm: feature 'temp' holds a message with fields (data), not a "
        "number: temp > 20 compares a message with a number, false with <, <=, >, >= and == "
        "and true with !=, whatever the message holds. Compare one of its "
        'fields: temp("data")'
    ) in r.stderr
    assert r.stderr.count("holds a message") == 1, r.stderr  # once, and not for 'east'
    rows = [json.loads(line) for line in r.stdout.splitlines()][:-1]
    east = [row["value"]["verdict"] for row in rows if row["label"] == "monitors/east"]
    # the nested field is read (x is 0, 1, 2): every state violates 'not x >= 0'
    assert east and not any(east)


def test_kpl_check_knows_the_labels_replay_feeds_from_a_recording(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``kpl check --recording``: what ``replay --kpl`` gets from the file exists.

    Before, ``kpl check`` alone refused a spec that ``replay --kpl`` ran: a recorded
    label it uses without declaring it is "unknown".
    """
    path = tmp_path / "station.mcap"
    w = RecordWriter(path)
    for k in range(3):
        t = k * NS_PER_S
        w.add("wind-speed", 10.0 + k, t, t + MS)  # a semantic label (below)
        w.add("car/speed", 20.0, t, t + MS)
        w.add("car/offset", 1.0, t, t + MS)
        w.add("car/offset_1s", 1.0, t, t + MS)  # recomputed by the spec, not fed
    w.close()
    spec = tmp_path / "app.kpl"
    spec.write_text(
        "source car/speed\n"  # declared: fed, not there before
        "stream car/offset_1s = car/offset with {sample_period: 1}\n"
    )
    check = ["kpl", "check", str(spec)]
    assert main(check) == 2
    assert "unknown label 'car/offset'" in capsys.readouterr().err
    assert main([*check, "--recording", str(path)]) == 0
    assert capsys.readouterr().out == "ok: 2 declarations\n"
    assert main(["replay", str(path), "--kpl", str(spec)]) == 0  # as replay has it
    capsys.readouterr()
    # a node's KPL names local labels: --config maps the recorded ones, as replay's does
    config = ROOT / "examples" / "node" / "station-python.toml"
    spec.write_text("stream wx/wind_1s = wx/wind with {sample_period: 1}\n")
    assert main([*check, "--recording", str(path)]) == 2
    assert "unknown label 'wx/wind'" in capsys.readouterr().err
    assert main([*check, "--recording", str(path), "--config", str(config)]) == 0
    assert capsys.readouterr().out == "ok: 1 declaration\n"
    assert main([*check, "--config", str(config)]) == 2
    assert "give --recording" in capsys.readouterr().err
    assert main([*check, "--recording", str(tmp_path / "none.mcap")]) == 2
    assert "none.mcap" in capsys.readouterr().err
    # the recording is checked first: before, a spec's syntax error was all that was said
    spec.write_text("stream = = nonsense\n")
    assert main([*check, "--recording", str(tmp_path / "none.mcap")]) == 2
    err = capsys.readouterr().err
    assert "none.mcap" in err and "app.kpl:" not in err, err
    assert main([*check, "--recording", str(spec)]) == 2  # a file, but no recording
    err = capsys.readouterr().err
    assert f"{spec}" in err and f"{spec}:1:" not in err, err


def test_replay_with_a_nodes_config_maps_the_recorded_labels_to_its_kpl(tmp_path: Path) -> None:
    """A recording holds semantic labels; ``--config`` replays them into the node's own KPL.

    Before, the node's application (local labels, ``wx/wind``) was fed nothing: "spec
    source 'wx/wind' is not in the recording".
    """
    path = tmp_path / "station.mcap"
    w = RecordWriter(path)
    for k in range(3):
        t = k * NS_PER_S
        w.add("wind-speed", 10.0 + k, t, t + MS)
        w.add("temperature", 20.0, t, t + 2 * MS)
    w.close()
    config = ROOT / "examples" / "node" / "station-python.toml"

    def run(*args: str, cwd: Path = tmp_path) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "federation.cli", "replay", str(path), *args, "--json"],
            capture_output=True,
            text=True,
            cwd=cwd,
            timeout=60,
        )

    # its CUs import from the current directory without --config
    bare = run("--kpl", "weather.kpl", "--print", "wx/wind_kmh", cwd=config.parent)
    assert bare.returncode == 0, bare.stderr
    assert "spec source 'wx/wind' is not in the recording" in bare.stderr
    assert "give the node's config (--config NODE.toml)" in bare.stderr
    # with it, from beside the node's KPL, as the node imports them
    mapped = run("--config", str(config), "--print", "wx/wind_kmh")
    assert mapped.returncode == 0, mapped.stderr
    assert (
        "'wx/wind' is not" not in mapped.stderr and "'wx/temperature' is not" not in mapped.stderr
    )
    rows = [json.loads(line) for line in mapped.stdout.splitlines()]
    assert [r["value"] for r in rows[:-1]] == [36.0, 39.6, 43.2]
    assert rows[-1]["summary"]["counts"] == {"wx/wind": 3, "wx/temperature": 3}
