"""examples/node run as a user would: a helper of the tests that start its station."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any
from unittest import mock

from agents.keys import gen_keys, trust_keys
from agents.transports import free_tcp_port
from federation.cli import main as cli_main

ROOT = Path(__file__).resolve().parent.parent
NODE_EXAMPLE = ROOT / "examples" / "node"
CLI = [sys.executable, "-m", "federation.cli"]


class Station:
    """examples/node copied to a temporary directory, on free ports, with its keys."""

    def __init__(self, tmp: Path, mqtt_port: int | None = None) -> None:
        self.dir = tmp / "node"
        shutil.copytree(NODE_EXAMPLE, self.dir)
        self.port = free_tcp_port()
        self.federation = f"weather-{uuid.uuid4().hex[:8]}"  # one of its own per test
        for conf in self.dir.glob("*.toml"):
            text = conf.read_text().replace("127.0.0.1:7450", f"127.0.0.1:{self.port}")
            text = text.replace('federation = "weather"', f'federation = "{self.federation}"')
            if mqtt_port is not None:
                text = text.replace("port = 1883", f"port = {mqtt_port}")
            conf.write_text(text)
        keys = self.dir / "keys"
        pubs = [gen_keys(name, keys)[2] for name in ("station", "operator")]
        trust_keys(keys / "trust.json", pubs, federation=self.federation)
        self.node: subprocess.Popen[str] | None = None
        self._said: list[str] | None = None  # the node's stderr lines, once followed
        self._said_more = threading.Condition()
        self._said_reader: threading.Thread | None = None
        # a runtime directory of its own: the local channels of this test's nodes
        runtime = tmp / "run"
        runtime.mkdir(mode=0o700)
        self.env = {**os.environ, "PYTHONUNBUFFERED": "1", "XDG_RUNTIME_DIR": str(runtime)}

    def start(self, kind: str) -> str:
        """``dyknow node --config station-KIND.toml``; its ready line."""
        self.node = self.spawn("node", "--config", f"station-{kind}.toml")
        assert self.node.stdout is not None
        ready = self.node.stdout.readline()  # bounded by the test's timeout
        assert f"station ready in federation {self.federation}" in ready, self.stop()[1]
        return ready

    def spawn(self, *args: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
        """``dyknow ARGS`` started in the station's directory, its output piped as text."""
        return subprocess.Popen(
            [*CLI, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=self.dir,
            env=self.env if env is None else env,
        )

    def command(
        self, *args: str, timeout: float, env: dict[str, str] | None = None
    ) -> subprocess.CompletedProcess[str]:
        """``dyknow ARGS`` run to its end in the station's directory, as a user would."""
        return subprocess.run(
            [*CLI, *args],
            capture_output=True,
            text=True,
            cwd=self.dir,
            env=self.env if env is None else env,
            timeout=timeout,
        )

    def dyknow(self, *args: str) -> Any:
        """A one-shot command as the operator; its JSON answer.

        Run in this process: the same code as ``dyknow``, without an interpreter's start
        (about half of a one-shot command's second); the node is the process of its own.
        """
        argv = [*args, "--config", str(self.dir / "operator.toml"), "--json", "--wait", "10"]
        out, err = io.StringIO(), io.StringIO()
        channels = {"XDG_RUNTIME_DIR": self.env["XDG_RUNTIME_DIR"]}
        with (
            mock.patch.dict(os.environ, channels),
            contextlib.redirect_stdout(out),
            contextlib.redirect_stderr(err),
        ):
            code = cli_main(argv)
        assert code == 0, err.getvalue()
        if args[0] == "stream":
            return [json.loads(line) for line in out.getvalue().splitlines()]
        return json.loads(out.getvalue())

    def latest(self, *labels: str, until: Callable[[dict[str, Any]], bool]) -> dict[str, Any]:
        """``dyknow ask LABELS -p station`` until the answer satisfies ``until`` (20 tries)."""
        answer: dict[str, Any] = {}
        for _ in range(20):
            answer = self.dyknow("ask", *labels, "--platform", "station")
            if until(answer):
                return answer
            time.sleep(0.5)  # the inputs are paced by the outside world, not by an event here
        raise AssertionError(f"no such answer: {answer}")

    def follow_stderr(self) -> None:
        """Gather the running node's stderr as it comes, for `said` (and `stop`'s answer)."""
        node = self.node
        assert node is not None and node.stderr is not None
        stream, node.stderr = node.stderr, None  # read by the thread, no more by communicate
        said: list[str] = []

        def read() -> None:
            for line in stream:
                with self._said_more:
                    said.append(line)
                    self._said_more.notify_all()

        self._said = said
        self._said_reader = threading.Thread(target=read, daemon=True)
        self._said_reader.start()

    def said(self, text: str, *, within: float) -> bool:
        """Whether the node writes a stderr line holding ``text`` (awaited at most ``within`` s).

        `follow_stderr` first: the lines are the ones it wrote since.
        """
        said = self._said
        assert said is not None, "follow_stderr() first"
        with self._said_more:
            return self._said_more.wait_for(
                lambda: any(text in line for line in said), timeout=within
            )

    def stop(self) -> tuple[str, str]:
        """SIGINT the node; its stdout and stderr."""
        node = self.node
        if node is None:
            return "", ""
        if node.poll() is None:
            node.send_signal(signal.SIGINT)
        try:
            out, err = node.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            node.kill()
            out, err = node.communicate(timeout=5)
        self.node = None
        if self._said is not None and self._said_reader is not None:
            self._said_reader.join(timeout=15)  # the node ended: its stderr ends too
            err = "".join(self._said)
            self._said = self._said_reader = None
        return out, err


def _samples(answer: dict[str, Any], label: str) -> list[Any]:
    result = answer.get(label)
    return result["samples"] if isinstance(result, dict) else []


def _stats(out: str) -> list[dict[str, Any]]:
    """The per-input / per-output counts a node prints when it stops."""
    rows = []
    for line in out.splitlines():
        if line.startswith("dyknow node: {"):
            rows.append(json.loads(line.removeprefix("dyknow node: ")))
    return rows
