"""The audit file has a size bound: rotated at ``max_bytes``, ``backups`` older files kept.

A flood of junk is audited within a budget (~200 records/s), which bounds the rate but
not the total: without rotation the file grew ~4.7 GB a day. Here: the bound holds with
real records, exactly ``backups`` old files are kept, no record is lost by a rotation
(only the oldest file goes, deliberately), a bad config value is refused naming its key,
and a real node flooded by a plain zenoh client keeps its audit within
(backups + 1) x bound on disk.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import orjson
import pytest
import zenoh
from _node_example import Station
from test_interface import federation, ia, serve, until

from agents import AuditLog, request
from federation import PlatformConfig, PlatformConfigError


def _files(path: Path) -> list[Path]:
    """The audit file and its backups, newest first (as numbered)."""
    backups = sorted(
        path.parent.glob(f"{path.name}.*"), key=lambda p: int(p.name.rsplit(".", 1)[1])
    )
    return ([path] if path.exists() else []) + backups


def _lines(path: Path) -> list[dict[str, Any]]:
    return [orjson.loads(line) for line in path.read_bytes().splitlines()]


def _decisions(files: list[Path]) -> list[dict[str, Any]]:
    """Every record but the rotation notes, oldest first."""
    out: list[dict[str, Any]] = []
    for f in reversed(files):
        out.extend(r for r in _lines(f) if r.get("stage") != "audit-rotated")
    return out


def test_the_file_rotates_at_the_bound_and_keeps_every_record(tmp_path: Path) -> None:
    """Each file stays within the bound, in whole records; together they hold every one."""
    path = tmp_path / "audit.jsonl"
    audit = AuditLog(path=path, platform="uav-b", max_bytes=2000, backups=100)
    for i in range(300):
        audit.record(verdict="dropped", reason=f"junk {i}", stage="unauthenticated")
        if i % 7 == 0:  # batches of several records, as the flush takes them
            audit.take()
    audit.take()
    files = _files(path)
    assert len(files) > 10
    for f in files:
        assert f.stat().st_size <= 2000
        assert f.read_bytes().endswith(b"\n")
    assert [r["reason"] for r in _decisions(files)] == [f"junk {i}" for i in range(300)]
    # each file after the first begins with a note naming where the records before went
    for f in files[:-1]:
        note = _lines(f)[0]
        assert note["stage"] == "audit-rotated" and note["verdict"] is None
        assert note["previous"] == "audit.jsonl.1"
        assert note["platform"] == "uav-b"
    # numbered 1, 2, … from the oldest file begun by a rotation: the chain, whatever the names
    assert [_lines(f)[0]["file"] for f in files[:-1]] == list(range(len(files) - 1, 0, -1))
    assert _lines(files[-1])[0]["stage"] != "audit-rotated"


def test_the_chain_of_files_is_followed_by_their_numbers_after_many_rotations(
    tmp_path: Path,
) -> None:
    """Each file begun by a rotation names its place, ``file``, which no later rename changes.

    ``previous`` is the name the records before went to when it was written (always
    ``.1``), stale once the files move up; ``file`` n follows ``file`` n - 1, so a reader
    given the files in any order (or names) puts them back in order and sees a gap.
    """
    path = tmp_path / "audit.jsonl"
    audit = AuditLog(path=path, platform="uav-b", max_bytes=1200, backups=5)
    for i in range(120):
        audit.record(verdict="dropped", reason=f"junk {i}")
        audit.take()
    files = _files(path)
    assert len(files) == 6  # rotated more often than it keeps files: the oldest went
    numbers = {}
    for f in files:
        note = _lines(f)[0]
        assert note["stage"] == "audit-rotated"
        assert note["previous"] == "audit.jsonl.1"  # as written, not as renamed since
        numbers[note["file"]] = f
    newest = max(numbers)
    assert newest > 6  # the count goes on past the backups kept
    # followed by number, newest first, each file's predecessor is the next one by name:
    # the chain is the files' order, and nothing is missing between the kept ones
    chain = [numbers[n] for n in range(newest, newest - 6, -1)]
    assert chain == files
    kept = [int(r["reason"].split()[1]) for r in _decisions(list(chain))]
    assert kept == list(range(kept[0], 120))

    # a new process on the same file goes on counting from the file's own record
    again = AuditLog(path=path, platform="uav-b", max_bytes=1200, backups=5)
    for i in range(120, 140):
        again.record(verdict="dropped", reason=f"junk {i}")
        again.take()
    assert _lines(path)[0]["file"] > newest
    assert [_lines(f)[0]["file"] for f in _files(path)] == list(
        range(_lines(path)[0]["file"], _lines(path)[0]["file"] - 6, -1)
    )


def test_the_audit_files_folder_is_made_at_the_first_write(tmp_path: Path) -> None:
    """A config's `audit = "audit/uav-b.jsonl"` works without making the folder first."""
    path = tmp_path / "audit" / "nested" / "uav-b.jsonl"
    audit = AuditLog(path=path, platform="uav-b")
    audit.record(verdict="dropped", reason="junk", stage="unauthenticated")
    audit.take()
    assert [r["reason"] for r in _lines(path)] == ["junk"]


def test_only_backups_old_files_are_kept_the_oldest_go(tmp_path: Path) -> None:
    """With ``backups`` 2, the file and .1, .2; what went is the oldest records only."""
    path = tmp_path / "audit.jsonl"
    audit = AuditLog(path=path, platform="uav-b", max_bytes=1500, backups=2)
    for i in range(200):
        audit.record(verdict="dropped", reason=f"junk {i}")
        audit.take()
    files = _files(path)
    assert [f.name for f in files] == ["audit.jsonl", "audit.jsonl.1", "audit.jsonl.2"]
    assert sum(f.stat().st_size for f in files) <= 3 * 1500
    kept = [int(r["reason"].split()[1]) for r in _decisions(files)]
    assert kept == list(range(kept[0], 200))  # the newest, none missing between
    assert kept[0] > 0

    # no backups: the full file is deleted, and the new one says so
    bare = tmp_path / "bare.jsonl"
    audit = AuditLog(path=bare, platform="uav-b", max_bytes=1500, backups=0)
    for i in range(50):
        audit.record(verdict="dropped", reason=f"junk {i}")
        audit.take()
    assert _files(bare) == [bare]
    note = _lines(bare)[0]
    assert note["previous"] is None and "deleted" in note["reason"]


def test_a_file_over_the_bound_from_before_is_rotated_at_the_first_write(tmp_path: Path) -> None:
    """A file grown by an earlier release (or a larger bound) is set aside, not appended to."""
    path = tmp_path / "audit.jsonl"
    old = b'{"old":1}\n' * 1000
    path.write_bytes(old)
    audit = AuditLog(path=path, platform="uav-b", max_bytes=4096, backups=1)
    audit.record(verdict="dropped", reason="new")
    audit.take()
    assert (tmp_path / "audit.jsonl.1").read_bytes() == old
    assert [r["reason"] for r in _lines(path)][1:] == ["new"]


def test_a_gap_left_by_a_crash_between_renames_loses_nothing(tmp_path: Path) -> None:
    """A crash after .2 -> .3 but before .1 -> .2 leaves .2 missing; the next rotation copes."""
    path = tmp_path / "audit.jsonl"
    for name, body in (("audit.jsonl.1", b'{"n":1}\n'), ("audit.jsonl.3", b'{"n":3}\n')):
        (tmp_path / name).write_bytes(body)
    path.write_bytes(b'{"n":0}\n' * 200)
    audit = AuditLog(path=path, platform="uav-b", max_bytes=1600, backups=3)
    audit.record(verdict="dropped", reason="next")
    audit.take()
    assert (tmp_path / "audit.jsonl.1").read_bytes() == b'{"n":0}\n' * 200
    assert (tmp_path / "audit.jsonl.2").read_bytes() == b'{"n":1}\n'
    assert (tmp_path / "audit.jsonl.3").read_bytes() == b'{"n":3}\n'


def test_the_count_goes_on_after_a_crash_left_a_file_without_its_record(
    tmp_path: Path,
) -> None:
    """A crash after a rotation's renames, before its record: the numbers do not restart.

    The file the restarted process writes has no rotation record; the next rotation
    numbers its file one more than the highest kept, so numbers never repeat and the
    unnumbered file sits between the two it came between.
    """
    path = tmp_path / "audit.jsonl"
    audit = AuditLog(path=path, platform="uav-b", max_bytes=1200, backups=5)
    for i in range(60):
        audit.record(verdict="dropped", reason=f"junk {i}")
        audit.take()
    before = _lines(path)[0]["file"]
    assert before >= 2
    # the crash: the files moved up as a rotation does, the new file never begun
    names = [path, *(path.with_name(f"audit.jsonl.{i}") for i in range(1, 6))]
    for i in range(5, 0, -1):
        if names[i - 1].exists():
            names[i - 1].replace(names[i])
    again = AuditLog(path=path, platform="uav-b", max_bytes=1200, backups=5)
    second = path.with_name("audit.jsonl.2")
    end = 60
    while not (second.exists() and _lines(second)[0].get("stage") != "audit-rotated"):
        # two rotations since the restart: the crash's file in the middle of those kept
        again.record(verdict="dropped", reason=f"junk {end}")
        again.take()
        end += 1
        assert end < 200, "the restarted log did not rotate twice"
    firsts = [_lines(f)[0] for f in _files(path)]
    numbers = [r.get("file") for r in firsts]
    unnumbered = [i for i, r in enumerate(firsts) if r.get("stage") != "audit-rotated"]
    assert len(unnumbered) == 1  # the file the crash left, now among the backups
    k = unnumbered[0]
    assert 0 < k < len(firsts) - 1  # in the middle of the chain
    numbered = [n for n in numbers if n is not None]
    assert len(set(numbered)) == len(numbered)  # no number given twice
    assert numbered == sorted(numbered, reverse=True)  # newest first, by name as by number
    assert numbers[k - 1] == numbers[k + 1] + 1  # it lies between two consecutive numbers
    assert min(numbered) > 0 and max(numbered) > before
    kept = [int(r["reason"].split()[1]) for r in _decisions(_files(path))]
    assert kept == list(range(kept[0], end))  # nothing lost around the crash


def test_a_record_longer_than_the_bound_is_written_alone(tmp_path: Path) -> None:
    """A record longer than the bound is not lost (nor looped on): it gets a file of its own."""
    path = tmp_path / "audit.jsonl"
    audit = AuditLog(path=path, platform="uav-b", max_bytes=100, backups=10)
    for i in range(3):
        audit.record(verdict="dropped", reason=f"{i} " + "x" * 300)
    audit.take()
    reasons = [r["reason"][0] for r in _decisions(_files(path))]
    assert reasons == ["0", "1", "2"]


def test_bad_bounds_are_refused_naming_the_key(tmp_path: Path) -> None:
    """The config names the key; the class says what is wrong."""
    base = {
        "name": "uav-a",
        "federation": "demo",
        "key": "k",
        "trust": "t",
        "vocabulary": {},
        "mapping": {},
    }
    cases = {
        "audit_max_bytes": (100, "-1", "64MiB"),
        "audit_backups": (-1, "many"),
    }
    for key, values in cases.items():
        for value in values:
            with pytest.raises(PlatformConfigError, match=rf"^uav-a.toml: {key}: "):
                PlatformConfig.from_dict({**base, key: value}, source="uav-a.toml")
    config = PlatformConfig.from_dict(base)
    assert (config.audit_max_bytes, config.audit_backups) == (64 * 1024 * 1024, 4)
    with pytest.raises(ValueError, match="max_bytes must be at least 1"):
        AuditLog(path=tmp_path / "a.jsonl", max_bytes=0)
    with pytest.raises(ValueError, match="backups must be 0 or more"):
        AuditLog(path=tmp_path / "a.jsonl", backups=-1)


async def test_an_interface_agent_rotates_its_audit_of_real_messages(tmp_path: Path) -> None:
    """Accepted messages audited through the Interface Agent: bounded files, none lost."""
    path = tmp_path / "audit.jsonl"
    async with federation("uav-a", "uav-b") as fed:
        pa = await fed.start("uav-a")
        pb = await fed.start("uav-b", audit_path=path, audit_max_bytes=4096, audit_backups=50)
        asker = await serve(pa, "asker", None)
        await serve(pb, "echo")
        for i in range(60):
            assert (await request(asker, "echo@uav-b", i, ontology="demo"))["echo"] == i
        audit = ia(pb).audit
        total = sum(audit.counts.values())
        await until(lambda: len(_decisions(_files(path))) == total, "every record on disk")
    files = _files(path)
    assert len(files) >= 3
    assert all(f.stat().st_size <= 4096 for f in files)
    decisions = _decisions(files)
    assert sum(r["verdict"] == "accepted" for r in decisions) >= 60
    assert all(r["sender"] == "asker@uav-a" for r in decisions if r["verdict"] == "accepted")


@pytest.mark.timeout(150)
def test_a_flooded_node_keeps_its_audit_within_the_bound(tmp_path: Path) -> None:
    """Junk on ``acl/station`` at a high rate for a few seconds, from a plain zenoh client.

    The node audits ~200 records a second of it (the unauthenticated budget), ~55 KB/s;
    with a 16 KiB bound and 2 backups the files on disk stay within 48 KiB however long
    it lasts, and the newest records are there.
    """
    bound, backups = 16384, 2
    station = Station(tmp_path)
    conf = station.dir / "station-python.toml"
    # top-level keys go before the first table
    conf.write_text(
        f'audit = "audit.jsonl"\naudit_max_bytes = {bound}\naudit_backups = {backups}\n'
        + conf.read_text()
    )
    path = station.dir / "audit.jsonl"
    session = None
    try:
        station.start("python")
        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"client"')
        cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{station.port}"]))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        session = zenoh.open(cfg)
        key = f"dyknow/{station.federation}/v1/acl/station"
        sent, start = 0, time.monotonic()
        while time.monotonic() - start < 4.0:
            for _ in range(100):
                session.put(key, b'{"junk": %d}' % sent)
                sent += 1
            time.sleep(0.01)  # ~10 000 a second
        rate = sent / (time.monotonic() - start)
        time.sleep(0.6)  # two audit flushes
    finally:
        if session is not None:
            session.close()
        _, err = station.stop()
    assert "Traceback" not in err, err
    files = _files(path)
    total = sum(f.stat().st_size for f in files)
    print(f"\n{sent} junk puts at {rate:.0f}/s: {len(files)} audit files, {total} bytes")
    assert [f.name for f in files] == ["audit.jsonl", "audit.jsonl.1", "audit.jsonl.2"]
    assert total <= (backups + 1) * bound
    assert all(f.stat().st_size <= bound for f in files)
    # each begun by a rotation: the first file, and more, went (the bound held, not luck)
    assert all(_lines(f)[0]["stage"] == "audit-rotated" for f in files)
    dropped = [r for r in _decisions(files) if r["verdict"] == "dropped"]
    assert dropped and all(r["platform"] == "station" for r in dropped)
