"""Recordings: the file format, Recorder, replay on a manual clock, dyknow record / replay."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path
from typing import Any

import msgpack
import pytest

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
)
from dyknow_core._record import MAGIC, settle
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
    path = tmp_path / "flight.dkr"
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
    assert (header.version, header.instance, header.clock) == (1, "uav-a", "ManualClock")
    assert header.start == 5 * NS_PER_S and header.labels == ["gps/pos", "camera/objects"]


async def test_every_stream_including_those_created_after_the_start(tmp_path: Path) -> None:
    path = tmp_path / "all.dkr"
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
        Recorder(DyKnowInstance(clock=ManualClock()), ["nope"], tmp_path / "x.dkr").start()
    assert not (tmp_path / "x.dkr").exists()
    with pytest.raises(RecordError, match="cannot be written"):
        RecordWriter(tmp_path / "missing" / "x.dkr")


async def test_batches_are_written_while_recording(tmp_path: Path) -> None:
    path = tmp_path / "batches.dkr"
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
    path = tmp_path / "cut.dkr"
    w = RecordWriter(path, instance="i", batch_size=3)
    for k in range(7):
        w.add("x", k, k, k)
    complete = path.stat().st_size  # two batches of 3 are written
    w.close()
    data = path.read_bytes()
    for cut in (complete + 3, len(data) - 1):  # mid frame header, mid payload
        path.write_bytes(data[:cut])
        rec = read_recording(path)
        assert [s[1] for s in rec] == [0, 1, 2, 3, 4, 5]
        assert rec.truncated and rec.info()["truncated"]
    path.write_bytes(data)
    rec = read_recording(path)
    assert [s[1] for s in rec] == list(range(7)) and not rec.truncated


def _frame(obj: Any) -> bytes:
    payload = msgpack.packb(obj)
    return struct.pack(">II", len(payload), zlib.crc32(payload)) + payload


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (None, "no such file"),
        ("dir", "is a directory"),
        (b"hello world, not a recording", "not a DyKnow recording"),
        (MAGIC + b"\x00\x00\x00\x05\x00\x00\x00\x00abcde", "corrupt header"),
        (MAGIC + b"\x00\x00", "corrupt header"),
        (MAGIC + _frame({"format": "dyknow-record", "version": 7}), "format version 7"),
        (MAGIC + _frame({"format": "something-else", "version": 1}), "corrupt header"),
    ],
)
def test_bad_files_are_refused_naming_the_file_and_the_problem(
    tmp_path: Path, content: Any, problem: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bad.dkr"
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


def test_a_corrupt_batch_is_an_error_after_the_good_ones(tmp_path: Path) -> None:
    path = tmp_path / "flip.dkr"
    w = RecordWriter(path, batch_size=2)
    for k in range(4):
        w.add("x", k, k, k)
    w.close()
    data = bytearray(path.read_bytes())
    data[-3] ^= 0xFF  # inside the last batch's payload
    path.write_bytes(bytes(data))
    got = []
    with pytest.raises(RecordError, match=r"batch 2 at byte \d+: corrupt \(checksum mismatch\)"):
        for s in read_recording(path):
            got.append(s.value)
    assert got == [0, 1]


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
    path = tmp_path / "live.dkr"
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
    path = tmp_path / "paced.dkr"
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
    path = tmp_path / "x.dkr"
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
    path = tmp_path / "live.dkr"
    live = asyncio.run(_live_run(path))
    spec = tmp_path / "app.kpl"
    spec.write_text(SPEC)

    assert main(["replay", "--info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["counts"]["car/speed"] == 40 and info["instance"] == "live"
    assert info["version"] == 1 and not info["truncated"]
    assert main(["replay", "--info", str(path)]) == 0
    text = capsys.readouterr().out
    assert "car/offset: 40" in text and "dyknow-record version 1" in text

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
        counted = tmp_path / "counted.dkr"
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
        signalled = tmp_path / "signalled.dkr"
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
