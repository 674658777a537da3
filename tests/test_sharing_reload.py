"""A node's ``[sharing]`` changed without a restart: SIGHUP re-reads it, exports it no longer
allows end, what it newly allows is served, a broken table leaves the policy in force; and
a member revoked while the node runs loses at the gateway what a reload closing it ends."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import queue
import signal
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import IO, Any

import pytest
from _node_example import Station, _samples

from federation import PlatformConfigError, SharingSettings, load_sharing
from federation._platform import sharing_changes

CONFIG = "station-python.toml"
ASK = ("--config", "operator.toml", "--json", "--wait", "10")
# temperature to the operator only; wind to nobody
ONLY_TEMPERATURE = """
[sharing]
default = "none"

[[sharing.rules]]
name = "thermometer"
labels = ["temperature"]
query = ["operator"]
stream = ["operator"]
"""
EVERYTHING = '\n[sharing]\ndefault = "members"\n'
NOTHING = '\n[sharing]\ndefault = "none"\n'


class Lines:
    """A pipe's lines, read by a thread of their own: waited for with a bound."""

    def __init__(self, pipe: IO[str] | None) -> None:
        assert pipe is not None
        self.seen: list[str] = []
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._thread = threading.Thread(target=self._read, args=(pipe,), daemon=True)
        self._thread.start()

    def _read(self, pipe: IO[str]) -> None:
        for line in pipe:
            self._lines.put(line)
        self._lines.put(None)

    def wait_for(self, text: str, timeout: float) -> str:
        """The first line from now on containing ``text``; AssertionError after ``timeout``."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self._lines.get(timeout=left)
            except queue.Empty:
                break
            if line is None:
                break
            self.seen.append(line)
            if text in line:
                return line
        raise AssertionError(f"no line with {text!r} within {timeout} s: {self.seen}")

    def rest(self, timeout: float = 5.0) -> str:
        """What is left once the pipe closed (bounded)."""
        self._thread.join(timeout)
        while not self._lines.empty():
            line = self._lines.get_nowait()
            if line is not None:
                self.seen.append(line)
        return "".join(self.seen)


class Node:
    """``dyknow node`` (or another platform command) of the station, with ``[sharing]`` as
    given, its output followed."""

    def __init__(self, tmp: Path, sharing: str, *command: str) -> None:
        """``command``: the ``dyknow`` command and its options (default: ``node``)."""
        self.station = Station(tmp)
        self.config = self.station.dir / CONFIG
        base = self.config.read_text()
        # the audit file: a top-level key, before the first table
        self._base = base.replace('application = "weather.kpl"\n', _AUDIT, 1)
        self.share(sharing)
        self.proc = self.station.spawn(*(command or ("node",)), "--config", CONFIG)
        self.out, self.err = Lines(self.proc.stdout), Lines(self.proc.stderr)
        self.out.wait_for("station ready in federation", 60)

    def share(self, sharing: str) -> None:
        """Write the config with ``sharing`` as its ``[sharing]`` table."""
        self.config.write_text(self._base + sharing)

    def hup(self, sharing: str) -> None:
        """Rewrite ``[sharing]`` and SIGHUP the node."""
        self.share(sharing)
        self.proc.send_signal(signal.SIGHUP)

    def audit(self) -> list[dict[str, object]]:
        """The node's audit records written so far."""
        path = self.station.dir / "audit.jsonl"
        if not path.exists():
            return []
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]

    def audit_until(
        self, want: Callable[[list[dict[str, object]]], bool], timeout: float = 15.0
    ) -> list[dict[str, object]]:
        """The node's audit records once ``want`` holds of them (or at ``timeout``): the node
        writes its file every audit interval, not at each record."""
        deadline = time.monotonic() + timeout
        while True:
            records = self.audit()
            if want(records) or time.monotonic() > deadline:
                return records
            time.sleep(0.1)

    def policy_records(self, verdicts: list[str], timeout: float = 15.0) -> list[dict[str, object]]:
        """The ``policy`` audit records once their verdicts are ``verdicts`` (written apart)."""

        def policy(records: list[dict[str, object]]) -> list[dict[str, object]]:
            return [r for r in records if r.get("stage") == "policy"]

        want = verdicts
        records = self.audit_until(lambda rs: [r["verdict"] for r in policy(rs)] == want, timeout)
        return policy(records)

    def ask(self, label: str) -> subprocess.CompletedProcess[str]:
        """``dyknow ask LABEL -p station`` as the operator."""
        return self.station.command("ask", label, "-p", "station", *ASK, timeout=60)

    def __enter__(self) -> Node:
        return self

    def __exit__(self, failed: type[BaseException] | None, *_: object) -> None:
        """Stop it; once the block passed, AssertionError unless it said so, cleanly."""
        out, err = self.stop()
        if failed is None:
            assert "station stopped" in out and "Traceback" not in err, err

    @contextlib.contextmanager
    def following(self, label: str) -> Iterator[subprocess.Popen[str]]:
        """``dyknow stream LABEL -p station`` as the operator, its samples arriving, until
        the block ends (then killed, if it still runs)."""
        follower = self.station.spawn("stream", label, "-p", "station", *ASK)
        try:
            Lines(follower.stdout).wait_for(label, 60)
            yield follower
        finally:
            if follower.poll() is None:
                follower.kill()
            follower.wait(timeout=10)

    def stop(self) -> tuple[str, str]:
        """SIGINT it; its stdout and stderr."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=5)
        return self.out.rest(), self.err.rest()


_AUDIT = 'application = "weather.kpl"\naudit = "audit.jsonl"\n'


def _served(done: subprocess.CompletedProcess[str], label: str) -> bool:
    return done.returncode == 0 and bool(_samples(json.loads(done.stdout), label))


def _ask_until_served(node: Node, label: str) -> None:
    for _ in range(20):  # the inputs are paced by the outside world (5 readings a second)
        done = node.ask(label)
        if _served(done, label):
            return
        assert done.returncode == 0, done.stderr
        time.sleep(0.5)
    raise AssertionError(f"{label} never served: {done.stdout} {done.stderr}")


@pytest.mark.timeout(180)
def test_a_label_refused_is_served_once_sighup_reloads_a_sharing_that_allows_it(
    tmp_path: Path,
) -> None:
    with Node(tmp_path, ONLY_TEMPERATURE) as node:
        refused = node.ask("wind-speed")
        assert refused.returncode != 0
        assert "sharing" in refused.stderr and "wind-speed" in refused.stderr, refused.stderr
        node.hup(EVERYTHING)
        line = node.out.wait_for("[sharing] reloaded", 30)
        assert "sharing.default 'none' -> 'members'" in line, line
        assert "rule 'thermometer' removed" in line, line
        _ask_until_served(node, "wind-speed")
        records = node.policy_records(["reloaded"])
        assert [r["verdict"] for r in records] == ["reloaded"], records
        assert node.proc.poll() is None


@pytest.mark.timeout(180)
def test_an_export_the_reloaded_sharing_forbids_ends_and_is_audited(tmp_path: Path) -> None:
    # the export runs: samples arrive
    with Node(tmp_path, EVERYTHING) as node, node.following("temperature") as follower:
        node.hup(NOTHING)
        node.out.wait_for("[sharing] reloaded", 30)
        ended = node.out.wait_for("ended: the reloaded [sharing] no longer allows it", 30)
        assert "'temperature' to operator" in ended, ended
        # the receiver was told: its import ended, and with it the command's stream
        follower.wait(timeout=30)
        records = node.policy_records(["reloaded", "ended"])
        assert [r["verdict"] for r in records] == ["reloaded", "ended"], records
        gone = [r for r in records if r["verdict"] == "ended"]
        assert gone and gone[0]["stream"] == "temperature" and gone[0]["to"] == "operator"
        assert "sharing policy was reloaded" in str(gone[0]["reason"]), gone
        assert gone[0]["code"] == "sharing-rule"
        # asked again, it is refused now
        assert node.ask("temperature").returncode != 0
        assert node.proc.poll() is None


def _hup_handled(pid: int) -> bool:
    """Whether process ``pid`` catches or ignores SIGHUP now (Linux: /proc)."""
    fields = dict(
        line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines()
    )
    mask = int(fields["SigCgt"], 16) | int(fields["SigIgn"], 16)
    return bool(mask & (1 << (signal.SIGHUP - 1)))


@pytest.mark.timeout(180)
@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc")
@pytest.mark.parametrize("command", ["node", "console", "foxglove"])
def test_a_sighup_while_the_node_starts_does_not_end_it_and_reloads_once_ready(
    tmp_path: Path, command: str
) -> None:
    station = Station(tmp_path)
    options = () if command == "node" else ("--port", "0")
    proc = station.spawn(command, "--config", CONFIG, *options)
    out, err = Lines(proc.stdout), Lines(proc.stderr)
    try:
        deadline = time.monotonic() + 60
        while proc.poll() is None and not _hup_handled(proc.pid):
            assert time.monotonic() < deadline, "SIGHUP never handled"
            time.sleep(0.005)
        # held from the start of `dyknow node`, long before it is ready
        assert out._lines.empty(), "ready before SIGHUP was handled"
        proc.send_signal(signal.SIGHUP)
        out.wait_for("station ready in federation", 60)
        line = out.wait_for("[sharing] reloaded", 30)  # the held one, replayed
        assert line.startswith(f"dyknow {command}: ") and "no change" in line, line
        assert proc.poll() is None
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)
    assert "station stopped" in out.rest() and "Traceback" not in err.rest()


@pytest.mark.timeout(180)
def test_a_truncated_or_foreign_config_on_sighup_is_refused_and_the_policy_stays(
    tmp_path: Path,
) -> None:
    with Node(tmp_path, ONLY_TEMPERATURE) as node:
        _ask_until_served(node, "temperature")
        whole = node.config.read_text()
        # an editor's half-written file: no [sharing] in it, which must not mean the defaults
        node.config.write_text(whole[: whole.index("vocabulary")])
        node.proc.send_signal(signal.SIGHUP)
        line = node.err.wait_for("[sharing] not reloaded", 30)
        assert "missing" in line, line
        # another platform's file
        node.config.write_text(whole.replace('name = "station"', 'name = "other"', 1))
        node.proc.send_signal(signal.SIGHUP)
        line = node.err.wait_for("[sharing] not reloaded", 30)
        assert "name: 'other' is not the running platform's 'station'" in line, line
        assert node.proc.poll() is None
        _ask_until_served(node, "temperature")  # the old policy: still served …
        assert node.ask("wind-speed").returncode != 0  # … and still refused
        assert not [r for r in node.audit() if r.get("stage") == "policy"]


@pytest.mark.timeout(180)
@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs")
def test_a_config_replaced_by_a_fifo_on_sighup_is_refused_and_the_node_serves(
    tmp_path: Path,
) -> None:
    with Node(tmp_path, ONLY_TEMPERATURE) as node:
        _ask_until_served(node, "temperature")
        node.config.unlink()
        os.mkfifo(node.config)  # no writer ever: a blocking read would wait for good
        node.proc.send_signal(signal.SIGHUP)
        line = node.err.wait_for("[sharing] not reloaded", 30)
        assert "is not a regular file" in line, line
        _ask_until_served(node, "temperature")  # the node serves, the old policy in force
        assert node.ask("wind-speed").returncode != 0
        assert node.proc.poll() is None


@pytest.mark.timeout(180)
def test_an_export_ended_by_a_rule_naming_40_platforms_ends_the_receivers_import(
    tmp_path: Path,
) -> None:
    with Node(tmp_path, EVERYTHING) as node, node.following("temperature") as follower:
        many = ", ".join(f'"platform-with-a-long-name-{i:02d}"' for i in range(40))
        # its refusal names the 40: far over an end marker's 1024 characters
        node.hup(
            f'\n[sharing]\ndefault = "none"\n\n[[sharing.rules]]\nname = "few"\n'
            f'labels = ["temperature"]\nstream = [{many}]\n'
        )
        node.out.wait_for("ended: the reloaded [sharing] no longer allows it", 30)
        follower.wait(timeout=30)  # the marker arrived: the import, and the command, ended
        gone = [r for r in node.policy_records(["reloaded", "ended"]) if r["verdict"] == "ended"]
        assert gone and "platform-with-a-long-name-39" in str(gone[0]["reason"]), gone


@pytest.mark.timeout(180)
@pytest.mark.parametrize(
    ("broken", "key", "why"),
    [
        ('\n[sharing]\ndefault = "none"\ncolour = "red"\n', "sharing.colour", "unknown key"),
        ("\n[sharing]\ndefault = 3\n", "sharing.default", "'members' or 'none'"),
        (
            '\n[sharing]\n[[sharing.rules]]\nlabels = ["wind*"]\nstream = "operator"\n',
            "sharing.rules[0].stream",
            "list",
        ),
        ('\n[sharing]\ngateway = "public"\n', "sharing.gateway", "'private' or 'protected'"),
    ],
)
def test_a_broken_sharing_on_sighup_keeps_the_node_and_the_policy_in_force(
    tmp_path: Path, broken: str, key: str, why: str
) -> None:
    with Node(tmp_path, ONLY_TEMPERATURE) as node:
        _ask_until_served(node, "temperature")
        node.hup(broken)
        line = node.err.wait_for("[sharing] not reloaded", 30)
        assert f"{node.config.name}: {key}: " in line and why in line, line
        assert str(node.config) in line or f"{CONFIG}:" in line, line
        assert len(line.strip().splitlines()) == 1
        assert node.proc.poll() is None
        _ask_until_served(node, "temperature")  # the old policy: still served …
        assert node.ask("wind-speed").returncode != 0  # … and still refused
        assert not [r for r in node.audit() if r.get("stage") == "policy"]


def test_load_sharing_validates_the_whole_file_and_names_the_key(tmp_path: Path) -> None:
    path = tmp_path / "node.toml"
    whole = 'name = "x"\nfederation = "f"\nkey = "k"\ntrust = "t"\nvocabulary = "v.toml"\n'
    whole += 'mapping = "m.toml"\n'
    path.write_text(whole + ONLY_TEMPERATURE)
    settings = load_sharing(path, name="x", federation="f")
    assert settings.default == "none" and settings.rules[0].name == "thermometer"
    # the rest of the file is validated too: a truncated or wrong file is no policy
    path.write_text('name = 3\nwhatever = "x"\n' + ONLY_TEMPERATURE)
    with pytest.raises(PlatformConfigError, match=r"node\.toml: "):
        load_sharing(path)
    path.write_text('name = "x"\n')  # cut short: not the defaults ("members")
    with pytest.raises(PlatformConfigError, match=r"node\.toml: .*missing"):
        load_sharing(path)
    path.write_text(whole)  # whole, but cut just before [sharing]: not the defaults
    with pytest.raises(PlatformConfigError, match=r"node\.toml: sharing: missing: a reload never"):
        load_sharing(path, name="x", federation="f", running=settings)
    # a node running on the defaults: a file without the table changes nothing
    assert load_sharing(path, name="x", federation="f", running=SharingSettings()) == (
        SharingSettings()
    )
    path.write_text(whole + "[sharing]\n")  # the defaults, asked for
    assert load_sharing(path, name="x", federation="f", running=settings) == SharingSettings()
    with pytest.raises(PlatformConfigError, match=r"node\.toml: name: 'x' is not .* 'y'"):
        load_sharing(path, name="y", federation="f")
    with pytest.raises(PlatformConfigError, match=r"node\.toml: federation: 'f' is not"):
        load_sharing(path, name="x", federation="g")
    path.write_text(whole + 'sharing = "open"\n')
    with pytest.raises(PlatformConfigError, match=r"node\.toml: sharing: must be a table"):
        load_sharing(path)
    path.write_text(whole + '[sharing]\naccept_for = ["uav b"]\n')
    with pytest.raises(PlatformConfigError, match=r"sharing\.accept_for\[0\]: 'uav b'"):
        load_sharing(path)
    path.write_text("[sharing\n")
    with pytest.raises(PlatformConfigError, match="not valid TOML"):
        load_sharing(path)


def test_sharing_changes_name_the_rules_added_and_removed_and_the_default() -> None:
    old = SharingSettings.model_validate(tomllib.loads(ONLY_TEMPERATURE)["sharing"])
    assert sharing_changes(old, old) == []
    new = SharingSettings.model_validate(
        {"default": "members", "rules": [{"labels": ["wind*"], "query": ["*"]}]}
    )
    assert sharing_changes(old, new) == [
        "sharing.default 'none' -> 'members'",
        "rule 'thermometer' removed",
        "rule (wind*) added",
    ]
    two = SharingSettings(rules=[*old.rules, *new.rules])
    back = SharingSettings(rules=[*new.rules, *old.rules])
    assert sharing_changes(two, back) == ["rules reordered"]


async def test_a_reload_whose_output_fails_goes_on_reloading(tmp_path: Path) -> None:
    from types import SimpleNamespace

    from federation._cli_net import _reload_on_hup

    path = tmp_path / "node.toml"
    path.write_text(
        'name = "x"\nfederation = "f"\nkey = "k"\ntrust = "t"\nvocabulary = "v.toml"\n'
        'mapping = "m.toml"\n' + ONLY_TEMPERATURE
    )
    reloaded: list[SharingSettings] = []

    async def reload_sharing(
        settings: SharingSettings, *, source: str
    ) -> tuple[list[str], list[tuple[str, str, str, str]]]:
        reloaded.append(settings)
        return ["sharing.default 'members' -> 'none'"], [("e1", "temperature", "operator", "r")]

    def say(text: str) -> None:
        raise BrokenPipeError(32, "Broken pipe")  # stdout's reader went away

    audited: list[dict[str, object]] = []
    p = SimpleNamespace(
        name="x",
        config=SimpleNamespace(federation="f", trust=tmp_path / "t.json"),  # none: said
        federation_agent=SimpleNamespace(sharing=SimpleNamespace(settings=SharingSettings())),
        interface=SimpleNamespace(audit=SimpleNamespace(record=lambda **r: audited.append(r))),
    )
    p.reload_sharing = reload_sharing
    hup = asyncio.Event()
    task = asyncio.create_task(_reload_on_hup(p, str(path), hup, say))  # type: ignore[arg-type]
    try:
        for n in (1, 2):
            hup.set()
            async with asyncio.timeout(10):
                while len(reloaded) < n:  # noqa: ASYNC110
                    await asyncio.sleep(0.01)
        await asyncio.sleep(0.05)
        assert not task.done()  # still reloading: what it could not say is logged
        # the trust file it could not read, audited each time though nobody read the line
        assert [(r["verdict"], r["code"]) for r in audited] == [("refused", "trust-file")] * 2
        assert all("no such trust file" in str(r["reason"]) for r in audited)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task  # stops without raising


GATEWAY_OPEN = '\n[sharing]\ngateway = "protected"\n'
GATEWAY_CLOSED = '\n[sharing]\ngateway = "private"\n'


@pytest.mark.timeout(180)
async def test_sighup_opens_and_closes_the_gateway_to_other_members(tmp_path: Path) -> None:
    from agents import Agent, Failed, Refused, request, subscribe
    from federation import FederationPlatform
    from federation._cli_common import wait_for_members

    node = Node(tmp_path, GATEWAY_CLOSED)
    listing = {"action": "list-labels"}
    try:
        operator = FederationPlatform.from_file(node.station.dir / "operator.toml")
        async with asyncio.timeout(150), operator:
            assert await wait_for_members(operator, "station", 30)
            tester = await operator.agents.add(Agent("tester"))

            async def ask() -> object:
                return await request(
                    tester, "gateway@station", listing, ontology="dyknow", timeout=10
                )

            with pytest.raises(Refused, match="access denied"):  # private: not even listed
                await ask()
            node.hup(GATEWAY_OPEN)
            line = await asyncio.to_thread(node.out.wait_for, "[sharing] reloaded", 30)
            assert "sharing.gateway 'private' -> 'protected'" in line, line
            labels = await ask()  # the next request is let in
            assert isinstance(labels, dict) and "wx/temperature" in labels["labels"], labels
            feed = await subscribe(
                tester, "gateway@station", {"label": "wx/temperature"}, ontology="dyknow"
            )
            first = await feed.get(timeout=30)  # samples flow to the other member
            assert isinstance(first, dict) and first["label"] == "wx/temperature", first
            create = {"action": "create-stream", "label": "wx/temperature", "output": "op/t"}
            created = await request(tester, "gateway@station", create, ontology="dyknow")
            assert created == {"label": "op/t", "source": "wx/temperature"}, created
            node.hup(GATEWAY_CLOSED)
            line = await asyncio.to_thread(node.out.wait_for, "[sharing] reloaded", 30)
            assert "sharing.gateway 'protected' -> 'private'" in line, line
            assert "gateway subscription of tester@operator to 'wx/temperature' ended" in line
            # and the stream it created there removed (its process and its label)
            assert "gateway stream 'op/t' created by tester@operator removed" in line, line
            # the subscriber is told, no more than an export's receiver
            with pytest.raises(Failed, match="sharing policy no longer allows it"):
                for _ in range(1000):  # informs sent before the end may come first
                    await feed.get(timeout=30)
            with pytest.raises(Refused, match="access denied"):
                await ask()
        verdicts = ["reloaded", "reloaded", "ended", "ended"]
        records = await asyncio.to_thread(node.policy_records, verdicts)
        assert [r["verdict"] for r in records] == verdicts, records
        ended, removed = records[2:]
        assert ended["code"] == "sharing-gateway" and ended["stream"] == "wx/temperature"
        assert ended["to"] == "operator" and ended["subscriber"] == "tester@operator"
        assert removed["code"] == "sharing-gateway" and removed["stream"] == "op/t"
        assert removed["to"] == "operator" and removed["creator"] == "tester@operator"

        def denied(records: list[dict[str, object]]) -> list[dict[str, object]]:
            return [r for r in records if "access denied" in str(r.get("reason"))]

        records = await asyncio.to_thread(node.audit_until, lambda rs: len(denied(rs)) >= 2)
        refused = denied(records)
        assert len(refused) == 2, refused  # one before the opening, one after the closing
        assert node.proc.poll() is None
    finally:
        out, err = await asyncio.to_thread(node.stop)
    assert "station stopped" in out and "Traceback" not in err, err


@contextlib.asynccontextmanager
async def _gateway_open(
    tmp_path: Path, *others: str
) -> AsyncIterator[tuple[Any, Any, Any, Any, list[Any]]]:
    """The station with its gateway open and the operator, in this process over zenoh: the
    station's platform, its ``wx/temperature`` source, an agent of its own (``local``) and
    one of the operator's (``tester``); and a ``tester`` of each member named in
    ``others`` (trusted as the operator is, joined as it does)."""
    from agents import Agent
    from agents.keys import gen_keys, trust_keys
    from federation import FederationPlatform
    from federation._cli_common import wait_for_members

    station = Station(tmp_path)
    path = station.dir / CONFIG
    path.write_text(path.read_text() + GATEWAY_OPEN)
    keys = station.dir / "keys"
    operator = (station.dir / "operator.toml").read_text()
    for name in others:
        trust_keys(keys / "trust.json", [gen_keys(name, keys)[2]])
        text = operator.replace('name = "operator"', f'name = "{name}"')
        (station.dir / f"{name}.toml").write_text(text.replace("operator.key", f"{name}.key"))
    here = FederationPlatform.from_file(path)
    there = FederationPlatform.from_file(station.dir / "operator.toml")
    async with contextlib.AsyncExitStack() as stack:
        s = await stack.enter_async_context(here)
        o = await stack.enter_async_context(there)
        members = [o]
        for name in others:
            p = FederationPlatform.from_file(station.dir / f"{name}.toml")
            members.append(await stack.enter_async_context(p))
        source = s.instance.add_source("wx/temperature")  # the application is `dyknow node`'s
        for member in members:
            assert await wait_for_members(member, "station", 30)
        local = await s.agents.add(Agent("local"))
        testers = [await m.agents.add(Agent("tester")) for m in members]
        yield s, source, local, testers[0], testers[1:]


@pytest.mark.timeout(120)
async def test_a_reload_closing_the_gateway_removes_what_other_members_created_there(
    tmp_path: Path,
) -> None:
    from agents import Agent, Refused, request

    async with asyncio.timeout(100), _gateway_open(tmp_path) as (s, _, local, tester, _):

        async def create(asker: Agent, output: str) -> object:
            content = {"action": "create-stream", "label": "wx/temperature", "output": output}
            return await request(asker, "gateway@station", content, ontology="dyknow", timeout=10)

        await create(tester, "op/t")
        await create(local, "station/t")
        assert {"gateway:op/t", "gateway:station/t"} <= set(s.instance.processes)
        changes, _ = await s.reload_sharing(SharingSettings(gateway="private"), source=CONFIG)
        assert changes == [
            "sharing.gateway 'protected' -> 'private'",
            "gateway stream 'op/t' created by tester@operator removed",
        ], changes
        # the other member's: its process and label gone, counted, audited
        assert "gateway:op/t" not in s.instance.processes
        assert not s.instance.has_label("op/t")
        assert s.gateway.gateway_stats.streams_removed == 1
        records = [r for r in s.interface.audit.records if r.get("stage") == "policy"]
        assert [r["verdict"] for r in records] == ["reloaded", "ended"], records
        removed = records[1]
        assert removed["code"] == "sharing-gateway" and removed["stream"] == "op/t"
        assert removed["to"] == "operator" and removed["creator"] == "tester@operator"
        assert "gateway stream 'op/t' created by tester@operator removed" in str(removed["reason"])
        # this platform's own: kept, and it may go on creating; the other member may not
        assert "gateway:station/t" in s.instance.processes
        assert s.gateway.service.created == {"station/t": "gateway:station/t"}
        await create(local, "station/t2")
        with pytest.raises(Refused, match="access denied"):
            await create(tester, "op/t")
        assert s.gateway.gateway_stats.streams_removed == 1


@pytest.mark.timeout(120)
async def test_a_reload_closing_the_gateway_keeps_a_stream_this_member_builds_on(
    tmp_path: Path,
) -> None:
    from agents import Agent, request, subscribe

    async with asyncio.timeout(100), _gateway_open(tmp_path) as (s, source, local, tester, _):

        async def create(asker: Agent, label: str, output: str) -> object:
            content = {"action": "create-stream", "label": label, "output": output}
            return await request(asker, "gateway@station", content, ontology="dyknow", timeout=10)

        await create(tester, "wx/temperature", "op/a")  # the other member's
        await create(local, "op/a", "station/b")  # this platform's, on top of it
        feed = await subscribe(local, "gateway@station", {"label": "station/b"}, ontology="dyknow")
        changes, _ = await s.reload_sharing(SharingSettings(gateway="private"), source=CONFIG)
        kept = "gateway stream 'op/a' created by tester@operator kept: read by gateway:station/b"
        assert changes == ["sharing.gateway 'protected' -> 'private'", kept], changes
        records = [r for r in s.interface.audit.records if r.get("stage") == "policy"]
        assert [r["verdict"] for r in records] == ["reloaded", "kept"], records
        record = records[1]
        assert record["code"] == "sharing-gateway" and record["stream"] == "op/a"
        assert record["creator"] == "tester@operator" and kept in str(record["reason"])
        assert s.gateway.gateway_stats.streams_removed == 0
        # station/b still gets its input through op/a
        source.push(21.5)
        sample = await feed.get(timeout=10)
        assert sample["label"] == "station/b" and sample["samples"][0][0] == 21.5, sample
        # now this platform's: the next reload closing the gateway leaves it alone
        await s.reload_sharing(SharingSettings(gateway="protected"), source=CONFIG)
        changes, _ = await s.reload_sharing(SharingSettings(gateway="private"), source=CONFIG)
        assert changes == ["sharing.gateway 'protected' -> 'private'"], changes
        assert {"gateway:op/a", "gateway:station/b"} <= set(s.instance.processes)
        await feed.cancel()


@pytest.mark.timeout(120)
async def test_a_member_revoked_loses_what_it_created_through_the_gateway(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from agents import Agent, request, subscribe

    async with (
        asyncio.timeout(100),
        _gateway_open(tmp_path, "ranger") as (s, source, local, tester, [ranger]),
    ):

        async def create(asker: Agent, label: str, output: str) -> object:
            content = {"action": "create-stream", "label": label, "output": output}
            return await request(asker, "gateway@station", content, ontology="dyknow", timeout=10)

        await create(tester, "wx/temperature", "op/t")  # the operator's: removed
        await create(tester, "wx/temperature", "op/a")  # the operator's, built on here: kept
        await create(local, "op/a", "station/b")
        await create(ranger, "wx/temperature", "rg/t")  # another member's: stays
        follow = {"label": "wx/temperature"}
        await subscribe(tester, "gateway@station", follow, ontology="dyknow")
        theirs = await subscribe(ranger, "gateway@station", {"label": "rg/t"}, ontology="dyknow")
        assert len(s.gateway.subscriptions) == 2
        caplog.set_level(logging.WARNING, logger="federation._gateway")
        # revoked while it runs: the trust store the station's Interface Agent holds
        assert s.interface.trust.remove("operator")
        # at once: its subscription ended, its stream gone (process and label), counted
        assert [key[0] for key in s.gateway.subscriptions] == ["tester@ranger"]
        assert "gateway:op/t" not in s.instance.processes
        assert not s.instance.has_label("op/t")
        assert s.gateway.gateway_stats.streams_removed == 1
        # the one this platform reads kept (now this platform's), the other member's stays
        assert {"gateway:op/a", "gateway:station/b", "gateway:rg/t"} <= set(s.instance.processes)
        assert s.gateway.service.created == {
            "op/a": "gateway:op/a",
            "station/b": "gateway:station/b",
            "rg/t": "gateway:rg/t",
        }
        records = [r for r in s.interface.audit.records if r.get("stage") == "trust"]
        verdicts = ["revoked", "ended", "ended", "kept"]  # first its sessions, forgotten
        assert [r["verdict"] for r in records] == verdicts, records
        assert all(r["code"] == "untrusted" and r["to"] == "operator" for r in records)
        _, ended, removed, kept = records
        assert ended["subscriber"] == "tester@operator" and ended["stream"] == "wx/temperature"
        assert removed["creator"] == "tester@operator" and removed["stream"] == "op/t"
        assert kept["creator"] == "tester@operator" and kept["stream"] == "op/a"
        assert "kept: read by gateway:station/b" in str(kept["reason"])
        assert "removed from the trust file" in str(removed["reason"])
        said = [r.getMessage() for r in caplog.records if "trust file" in r.getMessage()]
        assert (
            len(said) == 1
            and "gateway stream 'op/t' created by tester@operator removed" in (said[0])
        ), said
        # the other member is served on, through its own stream
        source.push(21.5)
        while True:  # samples before the push may come first
            sample = await theirs.get(timeout=10)
            if any(row[0] == 21.5 for row in sample["samples"]):
                break
        assert sample["label"] == "rg/t", sample
        await theirs.cancel()


@pytest.mark.timeout(180)
@pytest.mark.parametrize("command", ["console", "foxglove"])
def test_console_and_foxglove_reload_sharing_on_sighup_and_serve_on(
    tmp_path: Path, command: str
) -> None:
    node = Node(tmp_path, ONLY_TEMPERATURE, command, "--port", "0")
    url = node.out.seen[-1].rsplit(": ", 1)[1].strip()  # the ready line's, token included
    try:
        assert node.ask("wind-speed").returncode != 0
        node.hup(EVERYTHING)
        # as a node's: the trust file first, said in a line of its own, then [sharing]
        line = node.out.wait_for("trust file reloaded", 30)
        assert line.startswith(f"dyknow {command}: trust file reloaded from "), line
        line = node.out.wait_for("[sharing] reloaded", 30)
        assert line.startswith(f"dyknow {command}: [sharing] reloaded from {CONFIG}: "), line
        assert "sharing.default 'none' -> 'members'" in line, line
        _ask_until_served(node, "wind-speed")
        node.hup(ONLY_TEMPERATURE.replace('"none"', '"nobody"'))  # wrong: the policy stays
        line = node.err.wait_for("[sharing] not reloaded", 30)
        assert line.startswith(f"dyknow {command}: [sharing] not reloaded"), line
        assert "sharing.default" in line, line
        _ask_until_served(node, "wind-speed")
        assert node.proc.poll() is None
        if command == "console":  # its page is served on, with the token of its start
            import urllib.request

            with urllib.request.urlopen(url, timeout=10) as page:
                assert page.status == 200
    finally:
        out, err = node.stop()
    assert f"dyknow {command}: station stopped" in out and "Traceback" not in err, err


_HELD_WHEN = """
import json, signal, sys
from collections.abc import Callable
heavy = ("agents", "dyknow_core", "pydantic", "zenoh", "msgpack", "orjson")
seen: list[list[str]] = []
install: Callable[..., object] = signal.signal
def spy(signum, handler):
    if signum == signal.SIGHUP and not seen:
        seen.append(sorted(m for m in sys.modules if m.split(".")[0] in heavy))
    return install(signum, handler)
signal.signal = spy
from federation.cli import main
code = main([sys.argv[1], "--config", "no-such-config.toml"])
print(json.dumps({"code": code, "heavy": seen}))
"""


@pytest.mark.parametrize("command", ["node", "console", "foxglove"])
def test_sighup_is_held_before_the_entry_point_imports_anything_heavy(command: str) -> None:
    # a fresh interpreter through the entry point, with a missing config: the hold
    # comes first, before DyKnow, the agents, pydantic or zenoh are imported
    done = subprocess.run(
        [sys.executable, "-c", _HELD_WHEN, command],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parent.parent,
    )
    result = json.loads(done.stdout.splitlines()[-1])
    assert result["code"] != 0, done.stderr  # it did run the command: the config is missing
    assert result["heavy"] == [[]], result


@pytest.mark.timeout(300)
@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc")
def test_sighups_from_the_first_moment_until_ready_never_end_a_node(tmp_path: Path) -> None:
    for attempt in range(3):
        station = Station(tmp_path / str(attempt))
        proc = station.spawn("node", "--config", CONFIG)
        out, err = Lines(proc.stdout), Lines(proc.stderr)
        sent = 0
        try:
            deadline = time.monotonic() + 10
            while proc.poll() is None and not _hup_handled(proc.pid):  # the interpreter starts
                assert time.monotonic() < deadline, "SIGHUP never handled"
                time.sleep(0.0005)  # a pause, not a wait: 2 cores, the child must start
            ready = ""
            deadline = time.monotonic() + 60
            while not ready:  # one every 20 ms, whatever the node is doing meanwhile
                assert proc.poll() is None, f"ended by SIGHUP {sent}: {err.rest()}"
                assert time.monotonic() < deadline, f"not ready: {out.seen} {err.seen}"
                proc.send_signal(signal.SIGHUP)
                sent += 1
                with contextlib.suppress(AssertionError):
                    ready = out.wait_for("station ready in federation", 0.02)
            line = out.wait_for("[sharing] reloaded", 30)  # those held: applied once ready
            assert "no change" in line, line
            assert proc.poll() is None and sent > 1
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
            proc.wait(timeout=20)
        assert "station stopped" in out.rest() and "Traceback" not in err.rest()


@pytest.mark.timeout(120)
@pytest.mark.parametrize("fixed", [None, "public"])
async def test_a_gateway_visibility_the_program_set_stays_on_reload(
    tmp_path: Path, fixed: str | None
) -> None:
    from agents import Visibility
    from federation import FederationPlatform

    station = Station(tmp_path)
    path = station.dir / CONFIG
    platform = FederationPlatform.from_file(path, join=False, gateway_visibility=fixed)
    async with asyncio.timeout(100), platform as p:
        assert p.agents.df is not None
        assert p.gateway.visibility is Visibility(fixed or "private")
        wanted = "protected"
        changes, _ = await p.reload_sharing(SharingSettings(gateway=wanted), source=CONFIG)
        assert changes[0] == f"sharing.gateway 'private' -> '{wanted}'", changes
        (service,) = p.agents.df.search(provider=p.gateway.aid)
        if fixed is None:  # the config's: re-registered as the file now says
            assert service.visibility == wanted == p.gateway.visibility
        else:
            assert changes[1] == f"the Gateway Agent stays {fixed!r} (set by the program)"
            assert service.visibility == fixed == p.gateway.visibility


@pytest.mark.timeout(120)
async def test_a_failed_gateway_reload_changes_nothing_and_the_file_is_compared_with_the_gateway(
    tmp_path: Path,
) -> None:
    from agents import Visibility
    from federation import FederationPlatform

    station = Station(tmp_path)
    platform = FederationPlatform.from_file(station.dir / CONFIG, join=False)
    async with asyncio.timeout(100), platform as p:
        df = p.agents.df
        assert df is not None

        def entry() -> Visibility:
            (service,) = df.search(provider=p.gateway.aid)
            return service.visibility

        async def broken(*args: object) -> None:
            raise RuntimeError("injected: the directory event cannot be sent")

        df._changed = broken  # type: ignore[method-assign]
        try:
            with pytest.raises(RuntimeError, match="injected"):
                await p.reload_sharing(SharingSettings(gateway="protected"), source=CONFIG)
        finally:
            del df._changed
        # nothing changed: the gateway, its directory entry, the policy
        assert p.gateway.visibility is Visibility.PRIVATE is entry()
        assert p.config.sharing.gateway == "private"
        assert p.federation_agent.sharing.settings.gateway == "private"
        same, _ = await p.reload_sharing(SharingSettings(gateway="private"), source=CONFIG)
        assert same == [], same  # the file as before: no change, truly
        # the gateway opened by the program: the file's "private" is a change, though the
        # file is as before
        await p.gateway.set_visibility("protected", "opened by the program")
        changes, _ = await p.reload_sharing(SharingSettings(gateway="private"), source=CONFIG)
        assert changes == ["the Gateway Agent re-registered 'private' (it served 'protected')"]
        assert p.gateway.visibility is Visibility.PRIVATE is entry()


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="POSIX signals")
async def test_a_sighup_held_while_the_loop_takes_signals_is_applied_once() -> None:
    from federation import _hup

    loop = asyncio.get_running_loop()
    before = signal.getsignal(signal.SIGHUP)
    through = asyncio.Event()
    # the loop takes a signal (as `_stop_event`'s): each signal now also writes its number
    # to the loop's wakeup pipe, which the loop replays to a handler of its own, if any
    loop.add_signal_handler(signal.SIGUSR1, through.set)
    applied: list[int] = []
    try:
        _hup.hold_hup()
        os.kill(os.getpid(), signal.SIGHUP)  # held, and its number in the pipe
        _hup.on_hup(lambda: loop.call_soon_threadsafe(applied.append, 1))
        os.kill(os.getpid(), signal.SIGUSR1)  # behind the SIGHUP in the pipe
        async with asyncio.timeout(10):
            await through.wait()  # the loop read the pipe past the held SIGHUP
        assert applied == [1]  # the held one, once
        os.kill(os.getpid(), signal.SIGHUP)
        async with asyncio.timeout(10):
            while len(applied) < 2:  # noqa: ASYNC110
                await asyncio.sleep(0)  # call_soon_threadsafe: scheduled already
        assert applied == [1, 1]
        _hup.on_hup(None)
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN  # stopping: never a kill
        os.kill(os.getpid(), signal.SIGHUP)
        through.clear()
        os.kill(os.getpid(), signal.SIGUSR1)
        async with asyncio.timeout(10):
            await through.wait()
        assert applied == [1, 1]
    finally:
        _hup.on_hup(None)
        loop.remove_signal_handler(signal.SIGUSR1)
        signal.signal(signal.SIGHUP, before)


_LATEST = {"action": "get-latest", "labels": ["temperature"]}


async def _until(what: str, check: Any, timeout: float = 15.0) -> None:
    """Poll ``check`` (counters have no event to await) until true, within ``timeout`` s;
    AssertionError naming ``what`` if not."""
    try:
        async with asyncio.timeout(timeout):
            while not check():  # noqa: ASYNC110
                await asyncio.sleep(0.02)
    except TimeoutError:
        raise AssertionError(f"not within {timeout} s: {what}") from None


@pytest.mark.timeout(120)
async def test_a_live_export_to_a_platform_revoked_stops_and_nothing_more_is_sealed_for_it(
    tmp_path: Path,
) -> None:
    from agents import ReplyTimeout
    from federation import FederationPlatform
    from federation._cli_common import wait_for_members

    station = Station(tmp_path)
    s = FederationPlatform.from_file(station.dir / CONFIG)
    o = FederationPlatform.from_file(station.dir / "operator.toml")
    async with asyncio.timeout(100), s, o:
        source = s.instance.add_source("wx/temperature")  # the application is `dyknow node`'s
        assert await wait_for_members(o, "station", 30)
        export_id = await o.federation_agent.create_stream("station", ["temperature"], timeout=10)
        [export] = s.exporter.exports("operator")
        imported = o.importer.get("station", "temperature")
        assert imported is not None
        source.push(20.0)
        await _until("a sample imported", lambda: imported.received > 0)
        assert s.interface.sessions.sessions("operator")

        # revoked while it runs: the trust store the station's Interface Agent holds
        assert s.interface.trust.remove("operator")
        # at once: nothing can be sealed for it (no session; a key exchange is refused)
        assert s.interface.sessions.sessions("operator") == []
        assert s.interface.revoked == 1
        await _until("the export ended", lambda: s.revoked_exports == 1)
        assert not export.active and s.exporter.exports("operator") == []
        sent, received = export.sent, imported.received
        for value in (21.0, 22.0, 23.0):
            source.push(value)
        # the samples pushed after the revocation are the station's …
        assert "23.0" in repr(s.instance.latest("wx/temperature"))
        # … and none is sealed for the revoked platform any more
        assert export.sent == sent and imported.received == received
        with pytest.raises(Exception, match="not in the trust file"):
            await s.interface.agree("operator")  # no key exchange with it either
        # it asks on the session it still holds: refused, counted, audited
        unauthenticated = s.agents.stats.unauthenticated
        with pytest.raises(ReplyTimeout):
            await o.federation_agent.request_from("station", _LATEST, timeout=2)
        assert s.agents.stats.unauthenticated >= unauthenticated + 1
        [refused, *_] = [
            r
            for r in s.interface.audit.records
            if r.get("verdict") == "dropped" and r.get("stage") is None
        ]
        assert refused["from"] == "operator", refused
        assert str(refused["reason"]).startswith("untrusted: "), refused
        records = [r for r in s.interface.audit.records if r.get("stage") == "trust"]
        assert [r["verdict"] for r in records] == ["revoked", "ended"], records
        assert all(r["code"] == "untrusted" and r["to"] == "operator" for r in records)
        revoked, ended = records
        assert "1 session(s) with it forgotten" in str(revoked["reason"]), revoked
        assert ended["stream"] == "temperature" and ended["export"] == export_id, ended
        assert ended["reason"] == (
            f"export {export_id} of 'temperature' to operator ended: "
            "platform 'operator' was removed from the trust file (revoked)"
        ), ended

        # the other side revokes the station: its import from it ends there
        assert o.interface.trust.remove("station")
        await _until("the import ended", lambda: o.revoked_imports == 1)
        assert o.importer.get("station", "temperature") is None and imported.ended
        [gone] = [r for r in o.interface.audit.records if r.get("verdict") == "ended"]
        assert gone["stage"] == "trust" and gone["code"] == "untrusted"
        assert gone["from"] == "station" and gone["stream"] == "temperature", gone


def _trust_records(node: Node, verdicts: list[str], timeout: float = 15.0) -> list[dict[str, Any]]:
    """The node's ``trust`` audit records once their verdicts are ``verdicts`` (bounded)."""
    deadline = time.monotonic() + timeout
    while True:
        records = [r for r in node.audit() if r.get("stage") == "trust"]
        if [r["verdict"] for r in records] == verdicts or time.monotonic() > deadline:
            return records
        time.sleep(0.1)  # the audit file is flushed every 0.25 s


@pytest.mark.timeout(180)
async def test_a_member_removed_from_the_trust_file_on_sighup_is_refused_and_its_export_ends(
    tmp_path: Path,
) -> None:
    from agents import ReplyTimeout
    from federation import FederationPlatform
    from federation._cli_common import wait_for_members

    node = Node(tmp_path, EVERYTHING)
    keys = node.station.dir / "keys"
    try:
        operator = FederationPlatform.from_file(node.station.dir / "operator.toml")
        async with asyncio.timeout(150), operator:
            # a member streaming from the node and asking it, on a live session
            assert await wait_for_members(operator, "station", 30)
            export_id = await operator.federation_agent.create_stream(
                "station", ["temperature"], timeout=10
            )
            imported = operator.importer.get("station", "temperature")
            assert imported is not None
            await _until("samples imported", lambda: imported.received > 0, 30)
            assert await operator.federation_agent.request_from("station", _LATEST, timeout=10)
            # its operator revokes it: the key out of the node's trust file, SIGHUP
            untrust = node.station.command(
                "keys", "untrust", "--trust-file", "keys/trust.json", "operator", timeout=30
            )
            assert untrust.returncode == 0, untrust.stderr
            node.proc.send_signal(signal.SIGHUP)
            line = await asyncio.to_thread(node.out.wait_for, "trust file reloaded", 30)
            assert "revoked 'operator'" in line, line
            # its export ends there, audited
            records = await asyncio.to_thread(
                _trust_records, node, ["reloaded", "revoked", "ended"]
            )
            assert [r["verdict"] for r in records] == ["reloaded", "revoked", "ended"], records
            reloaded, revoked, ended = records
            assert "revoked 'operator'" in str(reloaded["reason"]), reloaded
            assert revoked["code"] == "untrusted" and revoked["to"] == "operator", revoked
            assert ended["code"] == "untrusted" and ended["export"] == export_id, ended
            assert ended["stream"] == "temperature" and ended["to"] == "operator", ended
            # its next request, sealed on the session it still holds, is refused there:
            # never answered, each envelope dropped and audited (the audit counts them)
            for _ in range(2):
                with pytest.raises(ReplyTimeout):
                    await operator.federation_agent.request_from("station", _LATEST, timeout=3)
            refused = await asyncio.to_thread(_untrusted, node, "operator", (None,), 2)
            assert len(refused) >= 2, refused
            assert all(r["verdict"] == "dropped" for r in refused), refused
            # nothing more streamed to it: its import stays where the revocation left it
            got = imported.received
            assert not [r for r in node.audit() if r.get("stage") == "trust" and r not in records]
        assert imported.received == got
        # a new process of it, without a session: its key exchange is refused, audited
        refused = node.ask("temperature")
        assert refused.returncode != 0 and "does it trust 'operator'" in refused.stderr, (
            refused.stderr
        )
        assert _untrusted(node, "operator", ("kx",), 1)
        # trusted again (its key back in the file), it is served after the next SIGHUP
        pub = keys / "operator.pub"
        again = node.station.command(
            "keys", "trust", "--trust-file", "keys/trust.json", str(pub), timeout=30
        )
        assert again.returncode == 0, again.stderr
        node.proc.send_signal(signal.SIGHUP)
        line = await asyncio.to_thread(node.out.wait_for, "trust file reloaded", 30)
        assert "trusted 'operator'" in line, line
        await asyncio.to_thread(_ask_until_served, node, "temperature")
        assert node.proc.poll() is None
    finally:
        out, err = await asyncio.to_thread(node.stop)
    assert "station stopped" in out and "Traceback" not in err, err


def _untrusted(node: Node, platform: str, stages: tuple[Any, ...], n: int) -> list[dict[str, Any]]:
    """The node's records of what ``platform`` sent refused as untrusted at ``stages``
    (None: an ACL envelope), once there are ``n`` (bounded)."""
    deadline = time.monotonic() + 15.0
    while True:
        records = [
            r
            for r in node.audit()
            if r.get("from") == platform
            and r.get("stage") in stages
            and str(r.get("reason")).startswith("untrusted: ")
        ]
        if len(records) >= n or time.monotonic() > deadline:
            return records
        time.sleep(0.1)  # the audit file is flushed every 0.25 s


@pytest.mark.timeout(180)
def test_a_broken_trust_file_on_sighup_keeps_the_node_and_the_trust_in_force(
    tmp_path: Path,
) -> None:
    with Node(tmp_path, EVERYTHING) as node:
        path = node.station.dir / "keys" / "trust.json"
        good = path.read_text()
        foreign = json.loads(good)
        foreign["federation"] = "elsewhere"
        broken = [
            ('{"v": 1, "federation": ', "not JSON"),
            (json.dumps(foreign), "'elsewhere'"),
            (None, "no such trust file"),
            ("fifo", "not a regular file"),
        ]
        _ask_until_served(node, "temperature")
        for content, why in broken:
            path.unlink(missing_ok=True)
            if content == "fifo":
                os.mkfifo(path)  # a read of it would never end
            elif content is not None:
                path.write_text(content)
            node.proc.send_signal(signal.SIGHUP)
            line = node.err.wait_for("trust file not reloaded", 30)
            assert "the trust in force stays" in line and why in line, line
            assert len(line.strip().splitlines()) == 1
            # the [sharing] reload that follows goes on as ever
            node.out.wait_for("[sharing] reloaded", 30)
            assert node.proc.poll() is None
        path.unlink(missing_ok=True)
        path.write_text(good)  # for the operator's own command: the node never re-read it
        _ask_until_served(node, "temperature")  # the operator is trusted still
        # each refusal audited (a file another federation's may be someone's attempt),
        # nothing reloaded, nobody revoked
        trust = [r for r in node.audit() if r.get("stage") == "trust"]
        assert [(r["verdict"], r["code"]) for r in trust] == [("refused", "trust-file")] * 4
        for record, (_, why) in zip(trust, broken, strict=True):
            assert record["reason"].startswith("trust file not reloaded, the trust in force")
            assert why in record["reason"], record


@pytest.mark.timeout(120)
async def test_a_reloaded_trust_file_revokes_rekeys_and_adds_and_a_wrong_one_changes_nothing(
    tmp_path: Path,
) -> None:
    from agents import KeyPair, TrustStore
    from federation import FederationPlatform

    station = Station(tmp_path)
    s = FederationPlatform.from_file(station.dir / CONFIG)
    async with asyncio.timeout(100), s:
        trust = s.interface.trust
        operator = trust.public_key("operator")
        other, ranger = KeyPair.generate("operator"), KeyPair.generate("ranger")
        mine = trust.public_key("station")
        wrong = [
            (TrustStore("elsewhere", {"station": mine}), "federation 'elsewhere'"),
            (
                TrustStore(trust.federation, {"station": KeyPair.generate("station").public_key}),
                "another key for 'station'",
            ),
        ]
        for store, why in wrong:
            with pytest.raises(ValueError, match=why):
                s.reload_trust(store, source="trust.json")
            assert list(trust) == ["operator", "station"]
            assert trust.public_key("operator") == operator
        assert not [r for r in s.interface.audit.records if r.get("stage") == "trust"]
        # the operator's key changed, the ranger added, this platform's own entry left out
        new = TrustStore(
            trust.federation, {"operator": other.public_key, "ranger": ranger.public_key}
        )
        changes = s.reload_trust(new, source="trust.json")
        assert changes == [
            "revoked and trusted with a new key 'operator'",
            "trusted 'ranger'",
            "'station' (this platform) is not in it: kept",
        ], changes
        assert list(trust) == ["operator", "ranger", "station"]
        assert trust.public_key("operator") == other.public_key
        assert trust.public_key("station") == mine
        assert s.interface.revoked == 1  # the old key's sessions are gone with it
        records = [r for r in s.interface.audit.records if r.get("stage") == "trust"]
        assert [r["verdict"] for r in records] == ["reloaded", "revoked"], records
        assert str(records[0]["reason"]).startswith("trust file reloaded from trust.json: ")
        # the same file again: no change
        assert s.reload_trust(new, source="trust.json") == [
            "'station' (this platform) is not in it: kept"
        ]
        assert s.interface.revoked == 1
