"""bench memory's node figures: a real ``dyknow node`` and a bare zenoh node, spawned once."""

from __future__ import annotations

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
    for words in lines:
        fields = dict(w.split("=", 1) for w in words[2:])
        assert float(fields["ours"]) > 0 and float(fields["zenoh-bare"]) > 0
        assert fields["better"] == "lower"
