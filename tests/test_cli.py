"""The ``dyknow`` CLI: keys, config errors, monitor/kpl, node + platforms."""

from __future__ import annotations

import json
import os
import re
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from agents._exceptions import UnknownPlatform
from agents._security import Handshake, KeyPair, TrustStore
from agents.keys import gen_keys, trust_keys
from agents.transports import free_tcp_port
from federation._cli_app import app
from federation.cli import main

runner = CliRunner()
ROOT = Path(__file__).resolve().parent.parent


def _free_port() -> int:
    # below the ephemeral range: a port from bind(0) may go to another connection first
    return free_tcp_port()


def _write_federation(tmp_path: Path, port: int) -> dict[str, Path]:
    """Keys, trust file, vocabulary, mappings and configs for uav-a and operator."""
    pubs = [gen_keys(name, tmp_path / "keys")[2] for name in ("uav-a", "operator")]
    trust_keys(tmp_path / "trust.json", pubs, federation="traffic")
    (tmp_path / "traffic.toml").write_text(
        'name = "traffic"\n[labels]\n"heli-altitude" = "altitude, m"\n'
    )
    configs = {}
    for name, transport in (
        ("uav-a", f'listen = ["tcp/127.0.0.1:{port}"]'),
        ("operator", f'connect = ["tcp/127.0.0.1:{port}"]'),
    ):
        (tmp_path / f"{name}-labels.toml").write_text(
            f'vocabulary = "traffic"\n[labels]\n"heli-altitude" = "{name}/alt"\n'
        )
        configs[name] = tmp_path / f"{name}.toml"
        configs[name].write_text(
            f'name = "{name}"\nfederation = "traffic"\nkey = "keys/{name}.key"\n'
            f'trust = "trust.json"\nvocabulary = "traffic.toml"\n'
            f'mapping = "{name}-labels.toml"\n\n[transport]\nmode = "peer"\n{transport}\n'
        )
    return configs


def test_keys_gen_and_trust(tmp_path: Path) -> None:
    keys, trust = tmp_path / "keys", tmp_path / "trust.json"
    r = runner.invoke(
        app,
        [
            *("keys", "gen", "--platform", "uav-a", "--dir", str(keys)),
            *("--trust-file", str(trust), "--federation", "traffic"),
        ],
    )
    assert r.exit_code == 0, r.output
    assert stat.S_IMODE((keys / "uav-a.key").stat().st_mode) == 0o600
    assert (keys / "uav-a.pub").exists()
    assert json.loads(trust.read_text())  # created, for federation traffic
    assert "traffic" in trust.read_text()
    # no overwrite without --force; with it, fine
    r = runner.invoke(app, ["keys", "gen", "--platform", "uav-a", "--dir", str(keys)])
    assert r.exit_code == 1
    r = runner.invoke(app, ["keys", "gen", "--platform", "uav-a", "--dir", str(keys), "--force"])
    assert r.exit_code == 0, r.output
    assert runner.invoke(app, ["keys", "gen", "-p", "uav-b", "-d", str(keys)]).exit_code == 0
    r = runner.invoke(app, ["keys", "trust", "--trust-file", str(trust), str(keys / "uav-b.pub")])
    assert r.exit_code == 0, r.output
    assert "uav-b" in r.output and "trusted" in r.output
    assert "uav-b" in trust.read_text()
    # a missing trust file without --federation: refused, exit 1
    r = runner.invoke(
        app, ["keys", "trust", "--trust-file", str(tmp_path / "no.json"), str(keys / "uav-b.pub")]
    )
    assert r.exit_code == 1


def test_keys_gen_refuses_a_trust_file_it_cannot_use_before_writing_keys(tmp_path: Path) -> None:
    keys, trust = tmp_path / "keys", tmp_path / "trust.json"
    trust_keys(trust, [gen_keys("uav-a", keys)[2]], federation="demo")
    for extra in (
        ("--trust-file", str(trust), "--federation", "traffic"),
        ("--trust-file", str(tmp_path / "no.json")),
    ):
        r = runner.invoke(app, ["keys", "gen", "-p", "uav-b", "-d", str(keys), *extra])
        assert r.exit_code == 1, r.output
        assert "'demo', not 'traffic'" in r.output or "give --federation" in r.output
        assert not (keys / "uav-b.key").exists()  # a retry is not told the key is there
    r = runner.invoke(
        app, ["keys", "gen", "-p", "uav-b", "-d", str(keys), "--trust-file", str(trust)]
    )
    assert r.exit_code == 0, r.output
    assert list(TrustStore.load(trust)) == ["uav-a", "uav-b"]


def test_tables_fold_what_an_80_column_terminal_cannot_hold(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from federation._cli_app import _print, _table

    monkeypatch.setenv("COLUMNS", "80")
    stamp = "2026-11-28T02:52:47.964+00:00"
    table = _table("get-latest from uav-a", "label", "query time", "value", "valid", "available")
    table.add_row("wind-speed-kmh", stamp, "20.808496403110213", stamp, stamp)
    _print(table)
    out = capsys.readouterr().out
    assert "…" not in out and max(map(len, out.splitlines())) <= 80
    body = [line.split("│")[1:-1] for line in out.splitlines() if line.startswith("│")]
    cells = ["".join(part.strip() for part in column) for column in zip(*body, strict=True)]
    assert cells == ["wind-speed-kmh", stamp, "20.808496403110213", stamp, stamp]


def test_platforms_keeps_a_service_name_on_one_line_at_80_columns(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A user copies a service name from ``dyknow platforms``: it is not folded in two."""
    from federation import _cli_app, _cli_net

    services = ["dyknow-federation", "dyknow-federation-discovery"]
    found = {
        name: [
            {"name": s, "type": "dyknow-federation", "provider": f"federation@{name}"}
            for s in services
        ]
        for name in ("uav-a", "traffic-management-centre")
    }

    async def list_platforms(config_path: str, wait: float) -> dict[str, Any]:
        return found

    monkeypatch.setattr(_cli_app, "_load", lambda config: None)
    monkeypatch.setattr(_cli_net, "list_platforms", list_platforms)
    monkeypatch.setenv("COLUMNS", "80")
    _cli_app.platforms(Path("uav-a.toml"))
    out = capsys.readouterr().out
    assert max(map(len, out.splitlines())) <= 80, out
    rows = [line.split("│") for line in out.splitlines() if line.startswith("│")]
    named = [row[2].strip() for row in rows if row[2].strip()]
    assert named == services * 2, out  # each whole on its row, no continuation line


def test_an_error_relayed_by_the_running_node_is_said_once(
    capsys: pytest.CaptureFixture[str],
) -> None:
    import typer

    from agents import ConversationError, Refused
    from federation._cli_app import _run_query
    from federation._cli_net import RelayedError
    from ontology import OntologyError, Refusal, UnknownSemanticLabel

    refusal = "federation@uav-a refused: label 'x': no stream for it here"
    unmapped = "semantic label 'x' has no mapping on this platform (not-mapped)"
    for error, said in [
        (RelayedError(refusal), refusal),  # the node's text, as it is
        # asked without a node: a platform's refusal, a label refused here, in their words
        (Refused(refusal), refusal),
        (UnknownSemanticLabel("x", Refusal.NOT_MAPPED), unmapped),
        (RuntimeError("a bug"), "RuntimeError: a bug"),  # unexpected: its kind tells what
        # an internal state, no refusal: its kind stays (before, it was said as a refusal)
        (
            ConversationError("conversation c1 is closed"),
            "ConversationError: conversation c1 is closed",
        ),
        (OntologyError("the fact feed is closed"), "OntologyError: the fact feed is closed"),
    ]:

        async def failing(error: Exception = error) -> None:
            raise error

        with pytest.raises(typer.Exit) as exit_:
            _run_query(failing())
        assert exit_.value.exit_code == 1
        assert capsys.readouterr().err == f"dyknow: {said}\n"


@pytest.mark.timeout(120)
def test_a_refusal_through_the_running_node_is_said_in_words(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before: ``dyknow: Refused: …``, ``dyknow: UnknownSemanticLabel: …``, the class first."""
    import asyncio
    import threading

    from federation import FederationPlatform, PlatformConfig
    from federation._local import LocalChannel

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))  # a socket of this test's own
    configs = _write_federation(tmp_path, _free_port())
    vocabulary = tmp_path / "traffic.toml"  # a label of the vocabulary nobody maps
    vocabulary.write_text(vocabulary.read_text() + '"heli-speed" = "speed, m/s"\n')
    ready, stop = threading.Event(), threading.Event()

    async def nodes() -> None:
        a = PlatformConfig.load(configs["uav-a"])
        op = PlatformConfig.load(configs["operator"])
        async with FederationPlatform(a), FederationPlatform(op) as p, LocalChannel(p):
            ready.set()
            while not stop.is_set():  # noqa: ASYNC110 (set by another thread)
                await asyncio.sleep(0.05)

    thread = threading.Thread(target=asyncio.run, args=(nodes(),))
    thread.start()
    try:
        assert ready.wait(60)
        base = ["heli-speed", "-c", str(configs["operator"]), "--wait", "10", "--timeout", "10"]
        unmapped = "semantic label 'heli-speed' has no mapping on this platform (not-mapped)"
        for command, platform, said in [
            ("ask", "uav-a", f"federation@uav-a refused: {unmapped}"),  # another's refusal
            ("stream", "operator", unmapped),  # the node's own label, refused there
        ]:
            assert main([command, *base, "-p", platform]) == 1
            assert capsys.readouterr().err == f"dyknow: {said}\n"
    finally:
        stop.set()
        thread.join(30)


def test_keys_untrust_revokes_and_show_lists(tmp_path: Path) -> None:
    keys, trust = tmp_path / "keys", tmp_path / "trust.json"
    for name in ("uav-a", "uav-b", "uav-c"):
        gen_keys(name, keys)
    trust_keys(trust, [keys / f"uav-{x}.pub" for x in "abc"], federation="traffic")
    pair_a, pair_b = KeyPair.load(keys / "uav-a.key"), KeyPair.load(keys / "uav-b.key")

    r = runner.invoke(app, ["keys", "show", "--trust-file", str(trust)])
    assert r.exit_code == 0, r.output
    assert "3 platform(s)" in r.output and pair_b.fingerprint in r.output

    # a typo is not a revocation: refused, naming it, and the file is unchanged
    before = trust.read_bytes()
    r = runner.invoke(app, ["keys", "untrust", "--trust-file", str(trust), "uav-b", "uav-bb"])
    assert r.exit_code == 1
    assert "'uav-bb'" in r.output and "nothing removed" in r.output
    assert trust.read_bytes() == before

    r = runner.invoke(app, ["keys", "untrust", "--trust-file", str(trust), "uav-b"])
    assert r.exit_code == 0, r.output
    assert "uav-b" in r.output and "removed" in r.output
    assert list(TrustStore.load(trust)) == ["uav-a", "uav-c"]
    r = runner.invoke(app, ["keys", "show", "--trust-file", str(trust)])
    assert "2 platform(s)" in r.output and "uav-b" not in r.output

    # a platform loading the new trust file refuses uav-b's key exchange (uav-b, still
    # trusting itself and uav-a, initiates as before)
    init = Handshake(pair_b, _trust_with(pair_a, pair_b)).initiate("uav-a")
    with pytest.raises(UnknownPlatform, match="uav-b"):
        Handshake(pair_a, TrustStore.load(trust)).respond(init)

    r = runner.invoke(app, ["keys", "untrust", "--trust-file", str(tmp_path / "no.json"), "x"])
    assert r.exit_code == 1 and "no such trust file" in r.output


def _trust_with(*pairs: KeyPair) -> TrustStore:
    return TrustStore("traffic", {p.platform: p.public_key for p in pairs})


def test_config_errors_name_file_and_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "uav-a"\nfederation = "traffic"\n[transport]\nlisten = ["nowhere"]\n')
    for command in ("node", "platforms"):
        assert main([command, "--config", str(bad)]) == 2
        err = capsys.readouterr().err
        assert f"{bad}: transport.listen:" in err and "Traceback" not in err
    assert main(["node", "--config", str(tmp_path / "missing.toml")]) == 2
    assert "cannot be read" in capsys.readouterr().err
    assert main(["ask", "x", "--platform", "uav-a", "--config", str(bad)]) == 2


def test_node_without_typer_reads_its_command_line_as_the_typer_command_does(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # `dyknow node -c FILE` is run without typer (_cli_node); its one option is typer's
    # node command's: the same flags, and only it (a new option needs the fast path too)
    import typer.main

    from federation._cli_node import CONFIG_FLAGS, node_config

    command = typer.main.get_command(app).commands["node"]  # type: ignore[attr-defined]
    assert [(p.name, tuple(p.opts), p.required) for p in command.params] == [
        ("config", CONFIG_FLAGS, True)
    ]
    for args in (
        ["node", "-c", "a.toml"],
        ["node", "--config", "a b.toml"],
        ["node", "--config=a.toml"],
        ["node", "--config=x=y.toml"],
    ):
        ctx = command.make_context("node", args[1:])
        assert node_config(args) == Path(ctx.params["config"]), args
    for args in (
        ["node"],
        ["node", "--help"],
        ["node", "-c"],
        ["node", "-c", "-x"],
        ["node", "--config="],
        ["node", "-ca.toml"],
        ["node", "-c", "a.toml", "--help"],
        ["node", "-c", "a.toml", "b"],
        ["console", "-c", "a.toml"],
        ["node", "--", "-c"],
        [],
    ):
        assert node_config(args) is None, args  # typer answers these
    # typer reads one variable of the environment before the command line: with it set,
    # typer answers (here that it completes nothing)
    with pytest.MonkeyPatch.context() as env:
        env.setenv("_DYKNOW_COMPLETE", "bash_complete")
        assert node_config(["node", "-c", "a.toml"]) is None
        assert main(["node", "-c", str(tmp_path / "missing.toml")]) == 1
        assert "cannot be read" not in capsys.readouterr().err
    # a missing config: the same message and exit code with and without typer
    missing = str(tmp_path / "missing.toml")
    assert main(["node", "-c", missing]) == 2
    fast = capsys.readouterr().err
    result = runner.invoke(app, ["node", "-c", missing])
    assert result.exit_code == 2 and "cannot be read" in fast
    assert fast.strip() in result.output


def test_node_whose_output_reader_went_away_exits_as_the_typer_command_does(
    tmp_path: Path,
) -> None:
    # a supervisor that stops reading: `dyknow node -c FILE` (without typer) and
    # `dyknow node -cFILE` (typer) both end with 1 and nothing on stderr, no traceback
    from _node_example import CLI, Station

    answers = []
    for i, form in enumerate((["-c", "station-file.toml"], ["-cstation-file.toml"])):
        (tmp_path / str(i)).mkdir()
        station = Station(tmp_path / str(i))
        r, w = os.pipe()
        os.close(r)  # nobody reads the node's stdout: its ready line meets a broken pipe
        try:
            done = subprocess.run(
                [*CLI, "node", *form],
                stdout=w,
                stderr=subprocess.PIPE,
                text=True,
                cwd=station.dir,
                env={**station.env, "PYTHONPATH": str(ROOT)},
                timeout=60,
            )
        finally:
            os.close(w)
        answers.append((done.returncode, done.stderr))
    assert answers == [(1, ""), (1, "")], answers


def test_monitor_and_kpl(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trace = tmp_path / "t.jsonl"
    trace.write_text('{"t": 0, "p": true}\n{"t": 1, "p": false}\n{"t": 2, "p": true}\n')
    assert main(["monitor", "always[0,1] p", "--trace", str(trace)]) == 0
    assert '"verdict": false' in capsys.readouterr().out
    assert main(["monitor", "speed <", "--trace", str(trace)]) == 2
    assert "dyknow monitor: formula:" in capsys.readouterr().err
    assert main(["kpl", "check", str(tmp_path / "missing.kpl")]) == 2
    assert "cannot read" in capsys.readouterr().err
    assert main(["monitor"]) == 2  # the formula and --trace are required: a usage error
    assert "Missing" in capsys.readouterr().err


def test_the_readmes_monitor_command_on_the_example_trace(
    capsys: pytest.CaptureFixture[str],
) -> None:
    formula = "always[0,10](speed < 30 -> eventually[0,5] on_road)"  # README.md, reasoning.md
    assert main(["monitor", formula, "--trace", str(ROOT / "examples" / "flight.jsonl")]) == 0
    verdicts = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    # off the road from 12 s to 19 s: the window from 11 s is violated, certain at 17 s
    assert verdicts == [
        {"t": 10, "from": 0, "verdict": True},
        {"t": 17, "from": 11, "verdict": False},
        {"t": 28, "from": 18, "verdict": True},
    ]


def test_parse_time() -> None:
    from federation._cli_time import asked, parse_time, when

    assert parse_time("now") == (0.0, True)
    assert parse_time("-2m") == (-120.0, True)
    assert parse_time("-500ms") == (-0.5, True)
    assert parse_time("12.5") == (12.5, False)
    # ISO 8601 with its offset, as the commands print times (or Z for UTC)
    t = 1_795_768_205.25  # 2026-11-27T08:30:05.250Z
    assert parse_time("2026-11-27T09:30:05.250+01:00") == (t, False)
    assert parse_time("2026-11-27T08:30:05.25Z") == (t, False)
    assert parse_time(when(t)) == (t, False)
    assert asked(t, False) == when(t) and asked(-90.0, True) == "now - 90 s"
    with pytest.raises(ValueError, match="ISO 8601 with its offset"):
        parse_time("yesterday")
    with pytest.raises(ValueError, match="has no UTC offset: add one"):
        parse_time("2026-11-27T09:30:05")


def test_ask_refuses_a_time_it_cannot_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # refused before anything is asked: no platform runs here
    configs = _write_federation(tmp_path, _free_port())
    ask = ["ask", "heli-altitude", "--platform", "uav-a", "--config", str(configs["operator"])]
    assert main([*ask, "--at", "2026-11-27T09:30:05"]) == 2
    assert "dyknow ask: '2026-11-27T09:30:05' has no UTC offset" in capsys.readouterr().err
    assert main([*ask, "--from", "noon"]) == 2
    assert "'noon' is not a time (ISO 8601 with its offset" in capsys.readouterr().err
    assert main([*ask, "--from", "2026-11-27T09:30:05Z", "--to", "now"]) == 2
    assert "both be relative or both absolute" in capsys.readouterr().err


@pytest.mark.timeout(40)
def test_asking_a_platform_that_is_not_running_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    configs = _write_federation(tmp_path, _free_port())  # uav-a is not started
    asked = ["heli-altitude", "--platform", "uav-a", "--config", str(configs["operator"])]
    quick = ["--wait", "0.5", "--timeout", "1"]
    for command in ("ask", "stream"):
        assert main([command, *asked, *quick]) == 1
        err = capsys.readouterr().err
        assert err.startswith(
            "dyknow: platform 'uav-a' was not seen in federation 'traffic' within 0.5 s (--wait)"
        ), err
        assert "is it running" in err and "Traceback" not in err


@pytest.mark.timeout(40)
def test_asking_a_platform_that_does_not_trust_us_says_what_to_check(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    configs = _write_federation(tmp_path, _free_port())
    # uav-a runs with the trust file of before the operator's key was added to it
    trust_keys(tmp_path / "trust-a.json", [tmp_path / "keys" / "uav-a.pub"], federation="traffic")
    text = configs["uav-a"].read_text()
    configs["uav-a"].write_text(text.replace('trust = "trust.json"', 'trust = "trust-a.json"'))
    node = subprocess.Popen(
        [sys.executable, "-m", "federation.cli", "node", "--config", str(configs["uav-a"])],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert node.stdout is not None
        assert "uav-a ready" in node.stdout.readline()  # bounded by the test's timeout
        asked = ["heli-altitude", "--platform", "uav-a", "--config", str(configs["operator"])]
        assert main(["ask", *asked, "--wait", "5", "--timeout", "2"]) == 1
        err = capsys.readouterr().err
        assert "did not answer the key exchange: it is alive, so does it trust 'operator'?" in err
        assert "send it SIGHUP after 'dyknow keys trust'" in err and "Traceback" not in err
    finally:
        _kill(node)


@pytest.mark.timeout(40)
def test_watching_a_platform_that_is_not_running_says_so_within_its_duration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    configs = _write_federation(tmp_path, _free_port())  # uav-a is not started
    assert main(["watch", "--config", str(configs["uav-a"]), "--duration", "1"]) == 1
    err = capsys.readouterr().err
    assert "platform 'uav-a' did not answer the watch request in 1 s (is it running" in err


def _kill(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait(5)


@pytest.mark.timeout(40)
def test_node_listed_by_platforms(tmp_path: Path) -> None:
    configs = _write_federation(tmp_path, _free_port())
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "federation.cli"]
    node = subprocess.Popen(
        [*cmd, "node", "--config", str(configs["uav-a"])],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env=env,
    )
    try:
        assert node.stdout is not None
        ready = node.stdout.readline()  # bounded by the test's timeout
        assert "uav-a ready in federation traffic" in ready, (
            node.stderr.read() if node.stderr else ""
        )
        listed = subprocess.run(
            [*cmd, "platforms", "--config", str(configs["operator"]), "--json", "--wait", "5"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env=env,
            timeout=20,
        )
        assert listed.returncode == 0, listed.stderr
        found = json.loads(listed.stdout)
        assert "uav-a" in found
        assert any(s["type"] == "dyknow-federation" for s in found["uav-a"]), found
        node.send_signal(signal.SIGINT)
        out, err = node.communicate(timeout=10)
        assert node.returncode == 0, err
        assert "uav-a stopped" in out and "Traceback" not in err
    finally:
        _kill(node)


PRODUCER = """
import asyncio, sys
from federation import FederationPlatform, PlatformConfig
async def run():
    async with FederationPlatform(PlatformConfig.load(sys.argv[1])) as p:
        src = p.instance.add_source("uav-a/alt")
        src.push(100.0)
        print("ready", flush=True)
        k = 1
        while True:
            await asyncio.sleep(0.1)
            src.push(100.0 + k)
            k += 1
asyncio.run(run())
"""


@pytest.mark.timeout(60)
def test_labels_ask_stream_against_a_producer(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
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
    op = ["--config", str(configs["operator"]), "--json"]

    def dyknow(*args: str) -> object:
        """``dyknow ARGS`` in this process: the same code, without an interpreter's start
        (about half of a one-shot command's second); the first command is a process."""
        code = main([*args, *op])
        out = capsys.readouterr()
        assert code == 0, out.err
        return json.loads(out.out) if "stream" not in args else out.out

    try:
        assert producer.stdout is not None
        assert producer.stdout.readline().strip() == "ready"
        labels = subprocess.run(
            [*cli, "labels", "--platform", "uav-a", *op],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env=env,
            timeout=20,
        )
        assert labels.returncode == 0, labels.stderr
        assert json.loads(labels.stdout) == {"labels": ["heli-altitude"]}
        latest = dyknow("ask", "heli-altitude", "--platform", "uav-a")
        assert isinstance(latest, dict) and latest["heli-altitude"]["samples"][0][0] >= 100.0
        history = dyknow("ask", "heli-altitude", "--platform", "uav-a", "--from", "-1m")
        assert isinstance(history, dict) and len(history["heli-altitude"]["samples"]) >= 2
        # --at in ISO 8601 with its offset, as the text output prints times
        from federation._cli_time import when

        at = when(time.time() - 0.05)
        value = dyknow("ask", "heli-altitude", "--platform", "uav-a", "--at", at)
        assert isinstance(value, dict) and value["heli-altitude"]["samples"][0][0] >= 100.0
        monkeypatch.setenv("COLUMNS", "200")
        code = main(["ask", "heli-altitude", "--platform", "uav-a", "--at", at, *op[:2]])
        text = capsys.readouterr()
        assert code == 0, text.err
        assert f"get-value-at {at} from uav-a" in text.out
        iso = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}[+-]\d\d:\d\d"
        row = next(line for line in text.out.splitlines() if "heli-altitude" in line)
        assert len(re.findall(iso, row)) == 3, row  # query time, valid, available
        out = dyknow("stream", "heli-altitude", "--platform", "uav-a", "--count", "2")
        rows = [json.loads(line) for line in str(out).splitlines()]
        assert len(rows) == 2 and all(r["label"] == "heli-altitude" for r in rows)
        assert rows[1]["value"] > rows[0]["value"]
    finally:
        _kill(producer)


@pytest.mark.timeout(90)
def test_a_command_reaches_the_node_of_its_own_key_only(tmp_path: Path) -> None:
    # two deployments on one host and one user's runtime directory, with the same
    # federation and platform names but keys and networks of their own: A runs uav-a and
    # operator, B runs operator only. Each config's command goes through its own operator.
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "XDG_RUNTIME_DIR": str(tmp_path / "run")}
    cmd = [sys.executable, "-m", "federation.cli"]
    a = _write_federation(tmp_path / "a", _free_port())
    b = _write_federation(tmp_path / "b", _free_port())
    procs: list[subprocess.Popen[str]] = []

    def start(config: Path) -> subprocess.Popen[str]:
        node = subprocess.Popen(
            [*cmd, "node", "--config", str(config)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env=env,
        )
        procs.append(node)
        assert node.stdout is not None
        ready = node.stdout.readline()  # bounded by the test's timeout
        assert " ready in federation traffic" in ready, node.stderr.read() if node.stderr else ""
        return node

    def platforms(config: Path) -> dict[str, Any]:
        listed = subprocess.run(
            [*cmd, "platforms", "--config", str(config), "--json", "--wait", "3"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env=env,
            timeout=30,
        )
        assert listed.returncode == 0, listed.stderr
        return dict(json.loads(listed.stdout))

    def stop(node: subprocess.Popen[str]) -> str:
        node.send_signal(signal.SIGINT)
        out, err = node.communicate(timeout=15)
        assert node.returncode == 0 and "Traceback" not in err, err
        return out

    try:
        start(a["uav-a"])
        operator_a = start(a["operator"])
        operator_b = start(b["operator"])  # started last: its name's socket was A's
        assert "uav-a" in platforms(a["operator"])  # A's network, through A's operator
        assert "uav-a" not in platforms(b["operator"])  # B's network, through B's operator
        assert "local channel: 1 commands served" in stop(operator_a)
        assert "local channel: 1 commands served" in stop(operator_b)
    finally:
        for p in procs:
            _kill(p)


@pytest.mark.timeout(60)
async def test_a_command_sends_nothing_to_a_node_of_another_key(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A node on the config's channel stating another key: refused, the request unsent."""
    import asyncio

    from federation import PlatformConfig
    from federation._local import ForeignNodeError, _hello, channel_path, via_node

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "run"))
    config_a = _write_federation(tmp_path / "a", _free_port())["operator"]
    a = PlatformConfig.load(config_a)
    b = PlatformConfig.load(_write_federation(tmp_path / "b", _free_port())["operator"])
    path = channel_path(a)
    assert path != channel_path(b) and path.parent == channel_path(b).parent  # same names
    received: list[bytes] = []

    async def impostor(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        # B's node, as if on A's channel (a hash collision, or a socket moved by hand)
        writer.write(json.dumps(_hello(b, KeyPair.load(b.key).public_key)).encode() + b"\n")
        await writer.drain()
        received.append(await reader.read())
        writer.close()

    path.parent.mkdir(parents=True, exist_ok=True)  # a long tmp_path: hashed into <tmp>
    server = await asyncio.start_unix_server(impostor, path=str(path))
    try:
        async with asyncio.timeout(50), server:
            with pytest.raises(ForeignNodeError, match="another deployment, so nothing was sent"):
                async for _ in via_node(a, {"op": "platforms"}):
                    pass
            command = await asyncio.create_subprocess_exec(
                *(sys.executable, "-m", "federation.cli", "platforms", "--config", str(config_a)),
                stdout=asyncio.subprocess.PIPE,
                stderr=asyncio.subprocess.PIPE,
                cwd=ROOT,
            )
            _, err = await command.communicate()
            assert command.returncode == 2, err
            assert b"dyknow: the node on " in err and b"nothing was sent to it" in err
            assert b"Traceback" not in err
            while len(received) < 2:  # noqa: ASYNC110 (the server's task has no event to await)
                await asyncio.sleep(0.01)
    finally:
        path.unlink()  # a server closed leaves its socket (shared <tmp> when hashed)
    assert received == [b"", b""]


@pytest.mark.timeout(40)
def test_console_serves_the_federation_it_sees(tmp_path: Path) -> None:
    # `dyknow console`: the operator's platform with its web console (the compose files'
    # operator runs it); the console lists the node it sees as a platform
    import urllib.request

    configs = _write_federation(tmp_path, _free_port())
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "federation.cli"]
    procs = [
        subprocess.Popen(
            [*cmd, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env=env,
        )
        for args in (
            ["node", "--config", str(configs["uav-a"])],
            ["console", "--config", str(configs["operator"]), "--port", "0"],
        )
    ]
    node, console = procs
    try:
        assert node.stdout is not None and console.stdout is not None
        assert "ready" in node.stdout.readline()
        ready = console.stdout.readline()  # bounded by the test's timeout
        assert "operator ready in federation traffic: http://127.0.0.1:" in ready, (
            console.stderr.read() if console.stderr else ""
        )
        login = ready.rsplit(": ", 1)[1].strip()  # http://127.0.0.1:<port>/?token=<token>
        url, token = login.split("?token=")
        with urllib.request.urlopen(login, timeout=5) as page:
            assert "operator console" in page.read().decode()
        names: list[str] = []
        bearer = {"Authorization": f"Bearer {token}"}
        for _ in range(100):  # the console learns members as they are seen
            asked = urllib.request.Request(url + "api/state", headers=bearer)
            with urllib.request.urlopen(asked, timeout=5) as answer:
                state = json.loads(answer.read())
            names = [p["name"] for p in state["platforms"]]
            if "uav-a" in names:
                break
            time.sleep(0.1)  # polling: the console has no event to await from here
        assert "uav-a" in names
        console.send_signal(signal.SIGINT)
        out, err = console.communicate(timeout=10)
        assert console.returncode == 0, err
        assert "operator stopped" in out and "Traceback" not in err
    finally:
        for p in procs:
            _kill(p)


async def test_commands_still_connected_end_with_the_local_channel(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A node that stops ends the commands connected to it: no task of theirs outlives it."""
    import asyncio

    from federation import FederationPlatform, PlatformConfig
    from federation._local import LocalChannel

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))  # a socket of this test's own
    config = PlatformConfig.load(_write_federation(tmp_path, _free_port())["uav-a"])
    async with asyncio.timeout(30):
        async with FederationPlatform(config, join=False) as p:
            channel = LocalChannel(p)
            async with channel:
                # one command connected and silent, one halfway through its request line
                silent = await asyncio.open_unix_connection(str(channel.path))
                halfway = await asyncio.open_unix_connection(str(channel.path))
                halfway[1].write(b'{"op": "platf')
                await halfway[1].drain()

                def serving() -> set[asyncio.Task[Any]]:
                    """The tasks serving a command (asyncio's server starts them)."""
                    return {
                        t
                        for t in asyncio.all_tasks()
                        if getattr(t.get_coro(), "__qualname__", "") == "LocalChannel._serve"
                    }

                while len(serving()) < 2:  # noqa: ASYNC110 (no event to await)
                    await asyncio.sleep(0.01)
                tasks = serving()
                assert {t.get_name() for t in tasks} == {"local[uav-a].command"}
            assert all(t.done() for t in tasks) and not serving()
            for reader, writer in (silent, halfway):
                # the node said who it is first (its key), then: the connection was closed
                assert json.loads(await reader.readline())["node"]["platform"] == "uav-a"
                assert await reader.read() == b""
                writer.close()


def test_a_formula_that_cannot_be_answered_is_said_so_before_asking(tmp_path: Path) -> None:
    """A malformed formula or a misspelt concept: exit 2 at once, as the console's 400."""
    configs = _write_federation(tmp_path, _free_port())
    vocabulary = tmp_path / "traffic.toml"
    vocabulary.write_text(vocabulary.read_text() + "[concepts]\nIncident = 2\nSegment = 1\n")
    base = ["labels", "-p", "uav-a", "-c", str(configs["operator"]), "--wait", "0.2"]
    r = runner.invoke(app, [*base, "--formula", "(all ?x (Incidnt ?x accident))"])
    assert r.exit_code == 2, r.output
    assert r.output.strip() == (
        "dyknow labels: --formula: unknown concept 'Incidnt' in (Incidnt ?x accident) "
        "(the vocabulary has: Incident, Segment)"
    )
    r = runner.invoke(app, [*base, "--formula", "(all ?x (Segment ?x)"])
    assert r.exit_code == 2, r.output
    assert "dyknow labels: --formula: this '(' is never closed (line 1, column 1)" in r.output


@pytest.mark.parametrize("command", ["ask", "stream", "record"])
def test_a_label_not_in_the_vocabulary_is_said_so_before_asking(
    tmp_path: Path, command: str
) -> None:
    """A misspelt label is named as such, not refused by the provider's sharing rules."""
    configs = _write_federation(tmp_path, _free_port())
    args = [command, "heli-altitude", "heli-altitud", "-p", "uav-a", "-c", str(configs["operator"])]
    if command == "record":
        args += ["--out", str(tmp_path / "out.mcap")]
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    assert "'heli-altitud' is not a label of the vocabulary traffic" in r.output
    assert not (tmp_path / "out.mcap").exists()


async def test_a_node_refuses_its_own_stream_at_a_period_an_export_refuses(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--sample-period`` under 1 ms on the node's own stream: refused, as an export is."""
    import asyncio

    from federation import FederationPlatform, PlatformConfig
    from federation._local import LocalChannel, via_node

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))  # a socket of this test's own
    config = PlatformConfig.load(_write_federation(tmp_path, _free_port())["uav-a"])
    request = {"op": "stream", "platform": "uav-a", "labels": ["x"], "sample_period": 0.0005}
    async with asyncio.timeout(30), FederationPlatform(config, join=False) as p, LocalChannel(p):
        lines = [line async for line in via_node(config, request)]
    refusal = "bad request: sample_period 0.0005 s is under 0.001 s, the finest an export takes"
    assert lines == [{"error": refusal}]


async def test_releases_cut_short_by_a_cancel_start_at_once_and_end_with_the_channel(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A command cancelled while giving its exports back: the rest start side by side,
    the cancel goes on at once, and none outlives the channel's end."""
    import asyncio

    from federation import FederationPlatform, PlatformConfig
    from federation._local import LocalChannel, _Shared

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))  # a socket of this test's own
    config = PlatformConfig.load(_write_federation(tmp_path, _free_port())["uav-a"])
    started: list[str] = []

    async def release(target: str, entry: _Shared) -> None:
        started.append(entry.export_id)
        await asyncio.sleep(3600)  # a cancel of the export that never comes back

    held = [_Shared(f"e{i}", ("uav-b", f"l{i}"), None) for i in range(3)]
    async with asyncio.timeout(30), FederationPlatform(config, join=False) as p:
        async with LocalChannel(p) as channel:
            channel._release = release  # type: ignore[method-assign]
            command = asyncio.create_task(channel._release_all("uav-b", held))
            while not started:  # noqa: ASYNC110 (no event to await)
                await asyncio.sleep(0.01)
            command.cancel()  # the node stopping
            async with asyncio.timeout(0.5):  # at once, not one release after another
                with pytest.raises(asyncio.CancelledError):
                    await command
            assert started == ["e0", "e1", "e2"]
            releasing = set(channel._releasing)
            assert len(releasing) == 3
        assert all(r.done() for r in releasing)  # cancelled by the channel's end


def test_platforms_help_says_it_shows_the_platforms_listed() -> None:
    """`dyknow platforms` shows the listed platforms (signed snapshot answered), not every
    one alive or a member by its events: its help says so, in the words of the docs."""
    r = runner.invoke(app, ["platforms", "--help"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    words = " ".join(r.output.split())
    assert "List the platforms listed in the federation" in words
    assert "signed directory snapshot answered" in words
    assert "platforms alive" not in words


async def test_each_declaration_of_a_node_tells_its_platform_when_the_transport_ends_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ended by the transport (MQTT: refused after a reconnection), each of the node's own
    declarations is logged, counted and kept as lost; before, none was heard of."""
    import asyncio

    from federation import FederationPlatform, PlatformConfig
    from federation._local import LocalChannel

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))  # a socket of this test's own
    config = PlatformConfig.load(_write_federation(tmp_path, _free_port())["uav-a"])
    async with (
        asyncio.timeout(30),
        FederationPlatform(config, join=False) as p,
        LocalChannel(p) as channel,
    ):
        agents = p.agents
        assert agents.df is not None
        handles = {
            "liveliness token": agents._token,
            "directory queryable": agents.df._queryable,
            "key-exchange queryable": p.interface._kx,
            "watch queryable": p.interface._watch_handle,
            "identity queryable": channel._handle,
        }
        told: list[str] = []
        agents.on_lost(lambda what, reason: told.append(f"{what}: {reason}"))
        for handle in handles.values():
            assert handle is not None
            handle._end("gone")
        kinds = {"liveliness token": "alive", "directory queryable": "df"}
        kinds |= {"key-exchange queryable": "kx", "watch queryable": "watch"}
        kinds |= {"identity queryable": "identity"}
        expected = [f"{what} dyknow/traffic/v1/{kind}/uav-a" for what, kind in kinds.items()]
        assert sorted(agents.lost) == sorted(expected)
        assert sorted(told) == sorted(f"{what}: gone" for what in expected)
        assert agents.stats.declarations_lost == 5


async def test_a_node_platforms_inbox_ended_by_its_transport_is_a_loss(tmp_path: Path) -> None:
    """Its Interface Agent's inbox ended by the transport (MQTT: refused after a
    reconnection), the platform ran on deaf, nothing logged or counted; a close is no loss."""
    import asyncio

    from federation import FederationPlatform, PlatformConfig

    config = PlatformConfig.load(_write_federation(tmp_path, _free_port())["uav-a"])
    async with asyncio.timeout(30), FederationPlatform(config, join=False) as p:
        agents = p.agents
        told: asyncio.Future[tuple[str, str]] = asyncio.get_running_loop().create_future()
        agents.on_lost(lambda what, why: told.done() or told.set_result((what, why)))
        # the inbox its consumer reads (the platform's task runs it in a guard)
        (task,) = [t for t in agents._tasks if t.get_name().endswith(".interface.inbox")]
        receive = task.get_coro().cr_frame.f_locals["coro"]  # type: ignore[union-attr]
        inbox = receive.cr_frame.f_locals["inbox"]
        inbox.inbox.close()  # as MQTT's `_end` does: the iterator ends, not closed
        async with asyncio.timeout(10):
            what, reason = await told
        assert what == "inbox subscription dyknow/traffic/v1/acl/uav-a"
        assert reason == "the transport ended the subscription"
        assert agents.stats.declarations_lost == 1
    assert agents.stats.declarations_lost == 1  # the close ended the rest: no loss


async def test_a_node_platforms_session_presence_watch_ended_by_its_transport_is_a_loss(
    tmp_path: Path,
) -> None:
    """Its Interface Agent's presence watch ended by the transport (MQTT: refused after a
    reconnection), the platform no longer saw others restart, nothing logged or counted."""
    import asyncio

    from federation import FederationPlatform, PlatformConfig

    config = PlatformConfig.load(_write_federation(tmp_path, _free_port())["uav-a"])
    async with asyncio.timeout(30), FederationPlatform(config, join=False) as p:
        agents = p.agents
        told: asyncio.Future[tuple[str, str]] = asyncio.get_running_loop().create_future()
        agents.on_lost(lambda what, why: told.done() or told.set_result((what, why)))
        (task,) = [t for t in agents._tasks if t.get_name().endswith(".interface.presence")]
        watch = task.get_coro().cr_frame.f_locals["coro"]  # type: ignore[union-attr]
        presence = watch.cr_frame.f_locals["presence"]
        presence.inbox.close()  # as MQTT's `_end` does: the iterator ends, not closed
        async with asyncio.timeout(10):
            what, reason = await told
        assert what == "session presence watch dyknow/traffic/v1/alive/*"
        assert reason == "the transport ended the subscription"
        assert agents.stats.declarations_lost == 1
    assert agents.stats.declarations_lost == 1  # the close ended the rest: no loss


async def test_a_declaration_ended_while_its_platform_closes_is_no_loss(tmp_path: Path) -> None:
    """Ended by the transport once the platform's close began (a node's SIGTERM), a
    declaration was counted lost, and the node that was asked to stop exited 1."""
    import asyncio

    from agents import Agent
    from federation import FederationPlatform, PlatformConfig

    config = PlatformConfig.load(_write_federation(tmp_path, _free_port())["uav-a"])

    class EndsTheKeyExchange(Agent):
        async def teardown(self) -> None:
            # the close stops the users' agents before the channel: the key exchange is
            # still declared, and the transport ends it now
            assert p.interface._kx is not None
            p.interface._kx._end("gone")

    told: list[str] = []
    async with asyncio.timeout(30), FederationPlatform(config, join=False) as p:
        await p.agents.add(EndsTheKeyExchange("ender"))
        p.agents.on_lost(lambda what, why: told.append(what))
    assert p.interface._kx is not None and p.interface._kx.ended == "gone"  # it ran
    assert told == [] and p.agents.lost == {}
    assert p.agents.stats.declarations_lost == 0


async def test_a_node_asked_to_stop_before_a_loss_exits_as_asked(tmp_path: Path) -> None:
    """A loss once SIGINT/SIGTERM asked the node to stop is logged and counted by the
    platform, but the node neither says it stops for it nor exits 1."""
    import asyncio

    from federation import FederationPlatform, PlatformConfig
    from federation._cli_net import _Losses

    config = PlatformConfig.load(_write_federation(tmp_path, _free_port())["uav-a"])
    async with asyncio.timeout(30), FederationPlatform(config, join=False) as p:
        stop = asyncio.Event()
        losses = _Losses(p, stop, "node")
        losses.started()
        stop.set()  # as the signal handler does
        assert p.agents.df is not None and p.agents.df._queryable is not None
        p.agents.df._queryable._end("gone")
        assert losses.lost == {}
        assert p.agents.stats.declarations_lost == 1


async def test_a_node_whose_declaration_is_lost_before_ready_fails_to_start(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A loss while the node starts said it ready, then stopped: it is a start failure,
    no ready line, the node closed and the error naming what was lost, and why."""
    import asyncio

    from federation import FederationPlatform, PlatformConfig
    from federation._cli_net import PlatformLostError, run_node

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))  # a socket of this test's own
    path = _write_federation(tmp_path, _free_port())["uav-a"]
    config = PlatformConfig.load(path)
    join = FederationPlatform.join
    opened: list[FederationPlatform] = []

    async def join_and_lose(self: FederationPlatform) -> None:
        await join(self)
        opened.append(self)
        assert self.agents.df is not None and self.agents.df._queryable is not None
        self.agents.df._queryable._end("refused")
        self.agents._token._end("refused")  # type: ignore[union-attr]
        assert self.interface._kx is not None
        self.interface._kx._end("gone")

    monkeypatch.setattr(FederationPlatform, "join", join_and_lose)
    said: list[str] = []
    with pytest.raises(PlatformLostError) as failed:
        async with asyncio.timeout(30):
            await run_node(config, str(path), said.append)
    assert not [line for line in said if "ready" in line], said
    assert str(failed.value) == (
        "platform 'uav-a' could not start: the transport ended its directory queryable "
        "dyknow/traffic/v1/df/uav-a, its liveliness token dyknow/traffic/v1/alive/uav-a "
        "(refused); its key-exchange queryable dyknow/traffic/v1/kx/uav-a (gone). "
        "Started again, it declares them anew"
    )
    (p,) = opened
    assert not p.agents.running  # closed


_LOGS = """
import logging, sys
from federation._cli_node import log_to_stderr
setup = sys.argv[1]
mine = logging.StreamHandler(sys.stderr)
mine.setFormatter(logging.Formatter("mine %(name)s: %(message)s"))
if setup != "none":
    logging.getLogger(None if setup == "root" else setup).addHandler(mine)
with log_to_stderr(), log_to_stderr():  # a command in a command adds nothing
    logging.getLogger("agents._platform").error("lost its inbox")
    logging.getLogger("federation._import").warning("a sender gone")
    logging.getLogger("agents._platform").info("below WARNING")
"""


@pytest.mark.parametrize(
    ("setup", "expected"),
    [
        (
            "none",
            ["ERROR agents._platform: lost its inbox", "WARNING federation._import: a sender gone"],
        ),
        (
            "root",
            ["mine agents._platform: lost its inbox", "mine federation._import: a sender gone"],
        ),
        # a program that configured only its own loggers: each record once
        (
            "agents",
            ["mine agents._platform: lost its inbox", "WARNING federation._import: a sender gone"],
        ),
        (
            "federation",
            ["ERROR agents._platform: lost its inbox", "mine federation._import: a sender gone"],
        ),
    ],
)
def test_the_log_goes_to_stderr_once_whichever_logger_the_process_configured(
    setup: str, expected: list[str]
) -> None:
    # a program that configured only the `agents` logger got its lines twice: its own
    # way, and again through the root's handler the commands added
    done = subprocess.run(
        [sys.executable, "-c", _LOGS, setup],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert done.stderr.splitlines() == expected


def test_the_log_goes_to_the_stderr_of_the_moment_as_pythons_last_resort_does() -> None:
    # a program that ran a command in-process with its stderr captured (a test runner's
    # CliRunner, redirect_stderr) lost every later record no handler took: the last
    # resort the command set wrote on to the capture, long gone
    script = (
        "import contextlib, io, logging\n"
        "from federation._cli_node import log_to_stderr\n"
        "running = contextlib.ExitStack()\n"
        "with contextlib.redirect_stderr(io.StringIO()):\n"
        "    running.enter_context(log_to_stderr())\n"
        "logging.getLogger('agents._platform').error('lost its inbox')\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert done.stderr.splitlines() == ["ERROR agents._platform: lost its inbox"]


def test_an_embedded_node_gives_back_the_last_resort_it_found() -> None:
    # a program embedding `run_node` kept the node's last resort after it returned: its
    # own later records no handler takes came out in the node's format, not Python's
    script = (
        "import logging, sys\n"
        "from pathlib import Path\n"
        "from federation._cli_node import run_node\n"
        "before = logging.lastResort\n"
        "code = run_node(Path(sys.argv[1]))\n"
        "print(code, logging.lastResort is before, flush=True)\n"
        "logging.getLogger('app').error('after the node')\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script, "missing-node.toml"],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        timeout=60,
    )
    assert done.stdout.splitlines() == ["2 True"], done.stderr
    # the config's error, then the program's record as Python's own last resort prints it
    assert done.stderr.splitlines()[-1] == "after the node", done.stderr
