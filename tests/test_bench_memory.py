"""bench memory's node figures: a real ``dyknow node`` and a bare zenoh node, spawned once."""

from __future__ import annotations

import os

import pytest

from bench import memory


@pytest.mark.timeout(120)
def test_node_ready_spawns_both_and_prints_the_lines(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(memory, "NODE_REPEAT", 1)
    monkeypatch.setattr(memory, "NODE_IDLE_S", 0.1)
    memory.node_ready()
    out = capsys.readouterr().out
    lines = [line.split() for line in out.splitlines() if line.startswith("BENCH ")]
    assert [words[1] for words in lines] == ["federation-node-ready", "federation-node-rss"]
    # the node's RSS split by part, one row each and their total (four columns of MB)
    split = out.partition("idle RSS by part")[2].splitlines()[1 : len(memory.RSS_PARTS) + 2]
    rows = {line[:46].strip(): [float(c) for c in line[46:].split()] for line in split}
    assert list(rows) == [*memory.RSS_PARTS, "total"]
    assert all(len(cells) == 4 for cells in rows.values())
    ours_total = rows["total"][0]
    assert abs(sum(rows[name][0] for name in memory.RSS_PARTS) - ours_total) < 0.1 * len(rows)
    assert rows["zenoh's library"][0] > 1 and rows["zenoh's library"][3] > 1
    # then each one's PSS and private memory: private <= PSS <= RSS, column by column
    shares = out.partition("idle RSS by part")[2].splitlines()[len(memory.RSS_PARTS) + 2 :][:2]
    pss, private = ([float(c) for c in line[46:].split()] for line in shares)
    assert shares[0].split()[0] == "PSS" and shares[1].split()[0] == "private"
    assert len(pss) == len(private) == 4
    for rss_mb, pss_mb, private_mb in zip(rows["total"], pss, private, strict=True):
        assert 1 < private_mb <= pss_mb + 0.1 and pss_mb <= rss_mb + 0.1
    for words in lines:
        fields = dict(w.split("=", 1) for w in words[2:])
        assert float(fields["ours"]) > 0 and float(fields["zenoh-bare"]) > 0
        assert fields["better"] == "lower"


def test_rss_parts_split_a_live_process_whole() -> None:
    """The split of a process's RSS adds up to the kernel's figure and names its libraries."""
    with open("/proc/self/status") as f:
        before = next(int(x.split()[1]) / 1024 for x in f if x.startswith("VmRSS:"))
    parts = memory.rss_parts(os.getpid())
    with open("/proc/self/status") as f:
        after = next(int(x.split()[1]) / 1024 for x in f if x.startswith("VmRSS:"))
    assert tuple(parts) == memory.RSS_PARTS
    assert before - 1 <= sum(parts.values()) <= after + 1  # read between the two, ±1 MB
    assert parts[memory.RSS_ANONYMOUS] > 1  # this interpreter's objects
    assert parts["the interpreter (libpython)"] + parts[memory.RSS_OTHER] > 1


def test_pss_private_of_a_live_process() -> None:
    """A process's PSS lies between its private memory and its RSS."""
    pss, private = memory.pss_private(os.getpid())
    with open("/proc/self/status") as f:
        rss = next(int(x.split()[1]) / 1024 for x in f if x.startswith("VmRSS:"))
    assert 1 < private <= pss + 0.1  # this interpreter's objects are its own
    assert pss <= rss + 1  # read around the same time, ±1 MB
