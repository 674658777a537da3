"""examples/outsider.py, a member written from docs/ alone, against a real `dyknow node`.

It joins the weather station's federation as `operator` (presence, signed directory
answers, a key exchange, encrypted envelopes), lists the station's labels, streams
one and decodes its batches, and answers the station's `dyknow ask`: the wire documents
are enough to do all of it, and stay so.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

from _node_example import ROOT, Station


def test_a_member_written_from_the_documents_joins_streams_and_answers(tmp_path: Path) -> None:
    station = Station(tmp_path)
    station.start("python")
    outsider = subprocess.Popen(
        [
            sys.executable,
            str(ROOT / "examples" / "outsider.py"),
            "--key",
            "keys/operator.key",
            "--trust",
            "keys/trust.json",
            "--connect",
            f"tcp/127.0.0.1:{station.port}",
            "--peer",
            "station",
            "--stream",
            "temperature",
            "--count",
            "3",
            "--serve",
            "60",
            "--value",
            "temperature=21.5",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=station.dir,
        env=station.env,
    )
    try:
        assert outsider.stdout is not None
        steps: dict[str, dict[str, Any]] = {}
        for line in outsider.stdout:  # bounded by the test's timeout
            step = json.loads(line)
            steps[step["step"]] = step
            if step["step"] == "serving":
                break
        assert steps.get("serving"), outsider.stderr.read() if outsider.stderr else ""
        assert any(s["provider"] == "federation@station" for s in steps["joined"]["peer_services"])
        assert "temperature" in steps["labels"]["content"]["labels"]
        assert steps["create-stream"]["performative"] == "inform"
        samples = steps["stream"]["samples"]
        assert len(samples) == 3
        assert all(isinstance(v, (int, float)) and isinstance(t, int) for v, t, _ in samples)
        assert steps["cancel-stream"]["performative"] == "inform"
        # the station asks the outsider: its key exchange, the outsider's answer
        asked = station.command(
            "ask",
            "temperature",
            "--platform",
            "operator",
            "--config",
            "station-python.toml",
            "--json",
            "--wait",
            "10",
            timeout=40,
        )
        assert asked.returncode == 0, asked.stderr
        assert [s[0] for s in json.loads(asked.stdout)["temperature"]["samples"]] == [21.5]
        outsider.send_signal(signal.SIGINT)
        out, err = outsider.communicate(timeout=15)
        assert outsider.returncode == 0, err
        assert json.loads(out.splitlines()[-1]) == {"step": "left"}
    finally:
        if outsider.poll() is None:
            outsider.kill()
            outsider.communicate(timeout=5)
        station.stop()


def test_the_outsider_imports_nothing_of_ours() -> None:
    """Written from the documents: plain libraries only, so it proves what they say."""
    source = (ROOT / "examples" / "outsider.py").read_text(encoding="utf-8")
    imported = {
        line.split()[1].split(".")[0]
        for line in source.splitlines()
        if line.startswith(("import ", "from "))
    }
    plain = {"__future__", "argparse", "base64", "hashlib", "hmac", "json", "os", "struct"}
    plain |= {"threading", "time", "typing", "msgpack", "nacl", "zenoh"}
    assert imported <= plain, imported
