"""Membership and the directory come only from authenticated sources (issue 11, item 9).

Real platforms: uav-a runs here (a `FederationPlatform` over real zenoh or MQTT), uav-b or
uav-c is a ``dyknow node`` process of its own. The attacker is an outsider with plain zenoh
or paho-mqtt and no key of the federation (or a key of its own that nobody trusts). Each
attack is refused or ignored, counted (``GlobalDirectory.refused``) and audited, in uav-a's
audit and, where it applies, in the victim's own audit file.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import multiprocessing
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import orjson
import paho.mqtt.client as paho
import pytest
import zenoh
from nacl.signing import SigningKey

from agents import DirectoryEvent, Refused, ReplyTimeout
from agents.keys import gen_keys, trust_keys
from agents.transports import Subscription, free_tcp_port
from federation import FederationPlatform, PlatformConfig

ROOT = Path(__file__).resolve().parent.parent
WAIT = 15.0
pytestmark = pytest.mark.timeout(90)


def _federation(tmp: Path, fed: str, names: list[str], transport: dict[str, str]) -> None:
    """Keys of ``names`` (all trusted), vocabulary, mappings and one config per platform."""
    pubs = [gen_keys(n, tmp / "keys")[2] for n in names]
    trust_keys(tmp / "trust.json", pubs, federation=fed)
    (tmp / "vocab.toml").write_text(f'name = "{fed}"\n[labels]\n"heli-altitude" = "m"\n')
    for n in names:
        (tmp / f"{n}-labels.toml").write_text(
            f'vocabulary = "{fed}"\n[labels]\n"heli-altitude" = "{n}/alt"\n'
        )
        (tmp / f"{n}.toml").write_text(
            f'name = "{n}"\nfederation = "{fed}"\nkey = "keys/{n}.key"\ntrust = "trust.json"\n'
            f'vocabulary = "vocab.toml"\nmapping = "{n}-labels.toml"\n'
            f'audit = "{n}-audit.jsonl"\n\n[transport]\n{transport[n]}\n'
        )


# ``dyknow node`` whose directory answers no query in time, as a loaded one's: each is held
# longer than any asker waits (its signed events still go out); it joins once the file
# ``<config>.join`` exists, so that its joining comes after its presence was taken
_SLOW_DIRECTORY = """
import asyncio, os, runpy, sys
from agents import DirectoryFacilitator
from federation._service import FederationAgent

async def _held(self, key, payload):
    await asyncio.sleep(3600)

go = sys.argv[-1] + ".join"
join = FederationAgent.join

async def _join_later(self):
    async def later():
        while not os.path.exists(go):
            await asyncio.sleep(0.05)
        await join(self)
    self.spawn(later(), "join-later")

DirectoryFacilitator._serve_public = _held
FederationAgent.join = _join_later
sys.argv = ["dyknow", *sys.argv[1:]]
runpy.run_module("federation.cli", run_name="__main__")
"""


@pytest.fixture
def node(tmp_path: Path) -> Iterator[Callable[..., subprocess.Popen[str]]]:
    """Start ``dyknow node`` for a platform of tmp_path; killed at the end.

    ``slow_directory``: its directory answers no query, and it joins once told
    (`_SLOW_DIRECTORY`).
    """
    procs: list[subprocess.Popen[str]] = []

    def start(name: str, *, slow_directory: bool = False) -> subprocess.Popen[str]:
        run = ["-c", _SLOW_DIRECTORY] if slow_directory else ["-m", "federation.cli"]
        proc = subprocess.Popen(
            [sys.executable, *run, "node", "--config", str(tmp_path / f"{name}.toml")],
            stdout=subprocess.PIPE,
            stderr=(tmp_path / f"{name}.err").open("w"),
            text=True,
            cwd=ROOT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        procs.append(proc)
        assert proc.stdout is not None
        line = proc.stdout.readline()  # bounded by the test's timeout
        assert "ready" in line, (tmp_path / f"{name}.err").read_text()
        return proc

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
        proc.wait(10)
        if proc.stdout is not None:
            proc.stdout.close()


async def _until(what: str, check: Callable[[], Any]) -> Any:
    deadline = time.monotonic() + WAIT
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {WAIT} s: {what}")
        await asyncio.sleep(0.05)


async def _up(directory: Subscription[DirectoryEvent], member: str) -> None:
    """Wait for ``member``'s ``platform-up``: its signed snapshot read, listed.

    A member by its signed events before that, and in ``platforms`` while its snapshot is
    asked; killed meanwhile, it is held unconfirmed: another case than a listed one
    (`test_a_forged_token_does_not_keep_a_member_never_listed_on_zenoh`).
    """
    async with asyncio.timeout(WAIT):
        async for event in directory:
            if event.op == "platform-up" and event.platform == member:
                return


def _audit(platform: FederationPlatform, stage: str, claimed: str) -> list[dict[str, Any]]:
    return [
        r
        for r in platform.interface.audit.records
        if r.get("stage") == stage and r.get("from") == claimed
    ]


def _stage(platform: FederationPlatform, stage: str) -> list[dict[str, Any]]:
    return [r for r in platform.interface.audit.records if r.get("stage") == stage]


def _file_audit(path: Path, stage: str, claimed: str) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    records = [json.loads(line) for line in path.read_text().splitlines() if line]
    return [r for r in records if r.get("stage") == stage and r.get("from") == claimed]


def _zenoh_outsider(port: int) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(conf)


async def _reaches(outsider: zenoh.Session, prefix: str, platform: str) -> None:
    """Wait until the outsider has a route to ``platform`` (peers do not forward for others)."""

    def answered() -> bool:
        replies = outsider.get(f"{prefix}/df/{platform}", timeout=1.0)
        return any(r.ok is not None for r in replies)

    deadline = time.monotonic() + WAIT
    while not await asyncio.to_thread(answered):
        assert time.monotonic() < deadline, f"the outsider never reached {platform}"
        await asyncio.sleep(0.1)


def _statement(fed: str, frm: str, kind: str, body: Any, key: SigningKey | None) -> bytes:
    """A directory statement as docs/wire.md spells it, signed with ``key`` (not trusted)."""
    obj: dict[str, Any] = {
        "v": 1,
        "fed": fed,
        "from": frm,
        "kind": kind,
        "boot": int(time.time() * 1000) + 10_000_000,  # "newer" than anything
        "seq": 1,
        "ts_ms": int(time.time() * 1000),
        "nonce": "",
        "body": orjson.dumps(body).decode(),
    }
    if key is not None:
        obj["sig"] = base64.b64encode(key.sign(b"anything").signature).decode()
    return orjson.dumps(obj)


async def test_outsiders_cannot_deregister_or_add_members_on_zenoh(
    tmp_path: Path, node: Callable[..., subprocess.Popen[str]]
) -> None:
    fed = f"member{os.getpid()}z"
    port = free_tcp_port()
    _federation(
        tmp_path,
        fed,
        ["uav-a", "uav-b", "uav-c"],
        {
            "uav-a": f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]',
            "uav-b": f'mode = "peer"\nconnect = ["tcp/127.0.0.1:{port}"]',
            "uav-c": f'mode = "peer"\nconnect = ["tcp/127.0.0.1:{port}"]',
        },
    )
    prefix = f"dyknow/{fed}/v1"
    async with (
        asyncio.timeout(4 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
    ):
        node("uav-b")
        await _until("uav-a sees uav-b", lambda: "uav-b" in a.members)
        gdf = a.agents.global_df
        assert gdf is not None
        before = before_services = len(gdf.services("uav-b"))
        assert before >= 1
        outsider = _zenoh_outsider(port)
        try:
            await _reaches(outsider, prefix, "uav-b")
            membership = a.membership()
            # 1. a deregister of uav-b's federation service, as the attacker sent it,
            #    then the same in today's format, unsigned and signed with a key nobody trusts
            service = gdf.services("uav-b")[0].to_obj()
            body = {"op": "deregister", "service": service}
            rogue = SigningKey.generate()
            forged = [
                orjson.dumps({"v": 1, **body}),
                _statement(fed, "uav-b", "df-event", body, None),
                _statement(fed, "uav-b", "df-event", body, rogue),
                _statement(fed, "uav-b", "df-event", {"op": "leave"}, rogue),
            ]
            refused, shed = gdf.refused, gdf.events_shed
            for payload in forged:
                outsider.put(f"{prefix}/df-events/uav-b", payload)
            # the junk and the unsigned one shed before any signature check, the two signed
            # with a rogue key refused by it
            await _until(
                "uav-a refused 4 forged events",
                lambda: (gdf.refused, gdf.events_shed) == (refused + 2, shed + 2),
            )
            await _until(
                "uav-a's audit of the forgeries", lambda: len(_audit(a, "df-events", "uav-b")) >= 3
            )
            records = _audit(a, "df-events", "uav-b")
            assert all(r["verdict"] == "dropped" for r in records)
            assert any("unsigned" in r["reason"] for r in records), records
            assert any("signature does not verify" in r["reason"] for r in records), records
            # uav-b's own view refused them too (its audit file)
            await _until(
                "uav-b's own audit of the forgeries",
                lambda: _file_audit(tmp_path / "uav-b-audit.jsonl", "df-events", "uav-b"),
            )
            assert "uav-b" in a.members and "uav-b" in gdf.platforms
            assert len(gdf.services("uav-b")) == before

            # 2. uav-x (not in the trust file) as token, DF answer and event; uav-c (trusted,
            #    not running) as a forged token: neither is listed
            refused, shed = gdf.refused, gdf.events_shed
            token_x = outsider.liveliness().declare_token(f"{prefix}/alive/uav-x")
            fake = _statement(fed, "uav-x", "df", [dict(service, provider="fed@uav-x")], rogue)
            queryable = outsider.declare_queryable(
                f"{prefix}/df/uav-x", lambda q: q.reply(f"{prefix}/df/uav-x", fake)
            )
            outsider.put(
                f"{prefix}/df-events/uav-x", _statement(fed, "uav-x", "df-event", body, rogue)
            )
            token_c = outsider.liveliness().declare_token(f"{prefix}/alive/uav-c")
            await _until("uav-x's presence audited", lambda: _audit(a, "presence", "uav-x"))
            await _until("uav-c's forged presence audited", lambda: _audit(a, "presence", "uav-c"))
            assert (
                "presence without a signed directory answer"
                in _audit(a, "presence", "uav-c")[0]["reason"]
            )
            # shed events are audited once per interval
            await _until("uav-x's event audited", lambda: _audit(a, "df-events", "uav-x"))
            assert "uav-x" not in gdf.platforms and "uav-c" not in gdf.platforms
            assert "uav-x" not in a.members and "uav-c" not in a.members
            assert not [s for s in gdf.services() if s.platform in ("uav-x", "uav-c")]
            # the forged token's end does not take uav-b's (nor anyone's) presence away
            token_b = outsider.liveliness().declare_token(f"{prefix}/alive/uav-b")
            token_b.undeclare()
            token_c.undeclare()
            token_x.undeclare()
            queryable.undeclare()
            # a marker on the same link, in order: once uav-x's new token is audited, the
            # ends of the tokens before it were seen (uav-x's end is audited too)
            marker = outsider.liveliness().declare_token(f"{prefix}/alive/uav-x")
            await _until("the marker", lambda: len(_audit(a, "presence", "uav-x")) == 3)
            marker.undeclare()
            assert [e for e in membership.inbox.drain() if e.platform == "uav-b"] == []
            assert "uav-b" in a.members and "uav-b" in gdf.platforms
            # uav-x up, uav-c's token, uav-x gone, uav-x up again: each counted once; uav-x's
            # event shed (a name not in the trust file) before any signature check
            assert gdf.refused == refused + 4
            assert gdf.events_shed == shed + 1

            # 3. a flood of forgeries is shed before the event loop and counted one by one,
            #    a few audited one by one, the rest summed up
            shed, before = gdf.events_shed, len(_audit(a, "df-events", "uav-b"))
            for _ in range(2000):  # none dropped at the sender: each must be counted
                outsider.put(
                    f"{prefix}/df-events/uav-b",
                    forged[1],
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
            await _until("2000 more shed", lambda: gdf.events_shed >= shed + 2000)
            assert gdf.event_gate is not None and gdf.event_gate.shed["unsigned"] >= 2001
            assert len(_audit(a, "df-events", "uav-b")) - before < 1000
            summary = await _until(
                "the summary records of what was shed",
                lambda: [
                    r
                    for r in a.interface.audit.records
                    if r.get("stage") == "df-events-shed"
                    and sum(x["count"] for x in _stage(a, "df-events-shed")) == gdf.events_shed
                ],
            )
            assert summary[-1]["verdict"] == "dropped"
            assert "unsigned" in summary[-1]["by_reason"]
            assert "uav-b" in a.members and len(gdf.services("uav-b")) == before_services
            membership.close()
        finally:
            outsider.close()


async def test_an_empty_retained_presence_does_not_drop_a_running_platform_on_mqtt(
    tmp_path: Path,
    node: Callable[..., subprocess.Popen[str]],
    mosquitto: tuple[str, int],
) -> None:
    host, port = mosquitto
    fed = f"member{os.getpid()}m"
    mqtt = f'kind = "mqtt"\nhost = "{host}"\nport = {port}'
    _federation(tmp_path, fed, ["uav-a", "uav-c"], {"uav-a": mqtt, "uav-c": mqtt})
    prefix = f"dyknow/{fed}/v1"
    async with (
        asyncio.timeout(4 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
    ):
        proc = node("uav-c")
        await _until("uav-a sees uav-c", lambda: "uav-c" in a.members)
        gdf = a.agents.global_df
        assert gdf is not None
        events = a.membership()
        attacker = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id="", protocol=paho.MQTTv5)
        attacker.connect(host, port)
        attacker.loop_start()
        try:
            refused = gdf.refused
            attacker.publish(f"{prefix}/alive/uav-c", b"", qos=1, retain=True).wait_for_publish(5)
            record = (
                await _until(
                    "uav-a audits the forged leave", lambda: _audit(a, "presence", "uav-c")
                )
            )[0]
            assert "without a signed leave" in record["reason"]
            assert gdf.refused == refused + 1
            assert "uav-c" in a.members and "uav-c" in gdf.platforms
            assert events.inbox.drain() == []  # no "gone": its exports were not stopped
            answer = await a.federation_agent.request_from(
                "uav-c", {"action": "list-labels"}, timeout=WAIT
            )
            assert answer is not None
            # uav-c announced itself again: a newcomer reads it alive (retained)
            seen: list[bytes] = []
            reader = paho.Client(paho.CallbackAPIVersion.VERSION2, protocol=paho.MQTTv5)
            reader.on_message = lambda c, u, m: seen.append(m.payload)
            reader.connect(host, port)
            reader.subscribe(f"{prefix}/alive/uav-c", qos=1)
            reader.loop_start()
            try:
                await _until("uav-c's presence retained again", lambda: seen)
            finally:
                reader.loop_stop()
                reader.disconnect()
            assert orjson.loads(seen[0]) == {"v": 1, "alive": True}
            # a real leave (the node stops) is still seen, signed
            proc.terminate()
            await _until("uav-c seen leaving", lambda: "uav-c" not in gdf.platforms)
        finally:
            attacker.loop_stop()
            attacker.disconnect()
            events.close()


async def test_a_forged_token_does_not_keep_a_dead_platform_listed_on_zenoh(
    tmp_path: Path, node: Callable[..., subprocess.Popen[str]]
) -> None:
    """zenoh keeps a key alive while any token holds it: the members are asked again."""
    fed = f"member{os.getpid()}k"
    port = free_tcp_port()
    _federation(
        tmp_path,
        fed,
        ["uav-a", "uav-b"],
        {
            "uav-a": f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]',
            "uav-b": f'mode = "peer"\nconnect = ["tcp/127.0.0.1:{port}"]',
        },
    )
    async with (
        asyncio.timeout(4 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
    ):
        gdf = a.agents.global_df
        assert gdf is not None
        gdf.recheck_interval = 1.0  # 30 s by default
        directory = gdf.watch()
        proc = node("uav-b")
        await _up(directory, "uav-b")
        directory.close()
        await _until("uav-a sees uav-b", lambda: "uav-b" in a.members)
        outsider = _zenoh_outsider(port)
        try:
            await _reaches(outsider, f"dyknow/{fed}/v1", "uav-a")
            token = outsider.liveliness().declare_token(f"dyknow/{fed}/v1/alive/uav-b")
            # the token reached uav-a before uav-b dies: a query sent after it on the same
            # link answered by uav-a, not a fixed pause
            await _reaches(outsider, f"dyknow/{fed}/v1", "uav-a")
            refused = gdf.refused
            proc.kill()
            killed = time.monotonic()
            await _until("uav-b taken for gone", lambda: "uav-b" not in gdf.platforms)
            print(f"uav-b gone {time.monotonic() - killed:.2f} s after SIGKILL (forged token held)")
            await _until("uav-a's members without uav-b", lambda: "uav-b" not in a.members)
            assert gdf.refused == refused + 1
            assert (
                "answered no signed directory query twice"
                in (_audit(a, "presence", "uav-b")[-1]["reason"])
            )
            token.undeclare()
        finally:
            outsider.close()


async def test_a_forged_token_does_not_keep_a_member_never_listed_on_zenoh(
    tmp_path: Path, node: Callable[..., subprocess.Popen[str]]
) -> None:
    """uav-b joins (its signed events taken) while its directory answers no query, and is
    SIGKILLed while uav-a still asks its first snapshot; an outsider holds a token under its
    name. Held unconfirmed, it is asked again by the rechecks too: answering none of two in
    a row, it is gone (counted, audited), its members told, the token held or not."""
    fed = f"member{os.getpid()}u"
    port = free_tcp_port()
    _federation(
        tmp_path,
        fed,
        ["uav-a", "uav-b"],
        {
            "uav-a": f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]',
            "uav-b": f'mode = "peer"\nconnect = ["tcp/127.0.0.1:{port}"]',
        },
    )
    interval = 1.0  # the recheck's (30 s by default)
    async with (
        asyncio.timeout(4 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
    ):
        gdf = a.agents.global_df
        assert gdf is not None
        gdf.recheck_interval = interval
        # each of the first snapshot's three queries waits this long: uav-b is killed well
        # within them, while uav-a holds it in `platforms`, not yet listed nor refused
        gdf.query_timeout = WAIT / 3
        outsider = _zenoh_outsider(port)
        async with a.membership() as events:
            try:
                await _reaches(outsider, f"dyknow/{fed}/v1", "uav-a")
                refused = gdf.refused
                proc = node("uav-b", slow_directory=True)
                await _until("uav-a asks uav-b's snapshot", lambda: "uav-b" in gdf.platforms)
                (tmp_path / "uav-b.toml.join").touch()  # its signed joining taken meanwhile
                await _until("uav-a takes uav-b's joining", lambda: "uav-b" in a.members)
                token = outsider.liveliness().declare_token(f"dyknow/{fed}/v1/alive/uav-b")
                # the token reached uav-a before uav-b dies: a query sent after it on the
                # same link answered by uav-a
                await _reaches(outsider, f"dyknow/{fed}/v1", "uav-a")
                under_way = "uav-b" in gdf.platforms and "uav-b" not in gdf.unconfirmed
                assert under_way, "uav-b's first snapshot no longer asked: nothing tested"
                assert gdf.refused == refused
                proc.kill()
                killed = time.monotonic()
                await _until("uav-b held unconfirmed", lambda: "uav-b" in gdf.unconfirmed)
                held = time.monotonic() - killed
                await _until("uav-a's members without uav-b", lambda: "uav-b" not in a.members)
                gone = time.monotonic() - killed
                print(
                    f"uav-b held unconfirmed {held:.2f} s after SIGKILL, gone {gone:.2f} s "
                    "after it (forged token held)"
                )
                # within the first snapshot's queries and two recheck intervals (each
                # recheck's query up to 5 s), not the token's lifetime
                assert gone - held < 3 * interval + 2 * 5.0, (held, gone)
                assert gdf.unconfirmed == [] and "uav-b" not in gdf.platforms
                assert gdf.services("uav-b") == [] and "uav-b" not in gdf._entries
                kinds = [e.kind for e in events.inbox.drain() if e.platform == "uav-b"]
                assert kinds == ["joined", "gone"], kinds
                # refused twice: its presence without a signed answer, then its silence
                assert gdf.refused == refused + 2
                reasons = [r["reason"] for r in _audit(a, "presence", "uav-b")]
                assert len(reasons) == 2, reasons
                assert "presence without a signed directory answer" in reasons[0]
                assert "answered no signed directory query twice" in reasons[1]
                assert "never listed" in reasons[1]
                # taken for gone, the token still held: its own task, asking it again, ends
                await _until("uav-b asked no more", lambda: "uav-b" not in gdf._presence_queues)
                assert "uav-b" not in a.members
                token.undeclare()
            finally:
                outsider.close()


async def test_a_forged_token_makes_no_stream_receiver_on_zenoh(
    tmp_path: Path, node: Callable[..., subprocess.Popen[str]]
) -> None:
    """An outsider holds a token under uav-b's name (uav-b not running) and a silent
    ``df/uav-b`` queryable, so uav-a asks its first snapshot for three query timeouts. A
    member, uav-c, asks uav-a to stream to uav-b meanwhile: refused as unlisted (counted,
    audited), nothing exported. The real uav-b, once its snapshot answered, is accepted."""
    fed = f"member{os.getpid()}r"
    port, port_c = free_tcp_port(), free_tcp_port()
    _federation(
        tmp_path,
        fed,
        ["uav-a", "uav-b", "uav-c"],
        {
            "uav-a": f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]',
            # peers forward for no one: uav-b asks uav-c to confirm, so it reaches it too
            "uav-b": (
                f'mode = "peer"\nconnect = ["tcp/127.0.0.1:{port}", "tcp/127.0.0.1:{port_c}"]'
            ),
            "uav-c": (
                f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{port_c}"]\n'
                f'connect = ["tcp/127.0.0.1:{port}"]'
            ),
        },
    )
    with (tmp_path / "uav-b.toml").open("a") as f:
        f.write('\n[sharing]\naccept_for = ["uav-c"]\n')  # the real uav-b consents
    async with (
        asyncio.timeout(6 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-c.toml")) as c,
    ):
        gdf = a.agents.global_df
        assert gdf is not None
        a.instance.add_source("uav-a/alt")  # what heli-altitude streams from
        await _until("uav-a lists uav-c", lambda: "uav-c" in gdf.listed)
        await _until("uav-c sees uav-a", lambda: "uav-a" in c.members)
        # each of the first snapshot's three queries waits this long: the whole attack
        # runs within them, while uav-b is in `platforms`, not yet listed nor refused
        gdf.query_timeout = WAIT / 3
        fed_a, fed_c = a.federation_agent, c.federation_agent
        outsider = _zenoh_outsider(port)
        try:
            await _reaches(outsider, f"dyknow/{fed}/v1", "uav-a")
            held: list[Any] = []  # a query dropped is ended: kept, it waits its timeout
            silent = outsider.declare_queryable(f"dyknow/{fed}/v1/df/uav-b", held.append)
            token = outsider.liveliness().declare_token(f"dyknow/{fed}/v1/alive/uav-b")
            await _until("uav-a asks uav-b's snapshot", lambda: held and "uav-b" in gdf.platforms)
            assert "uav-b" not in gdf.listed and "uav-b" not in gdf.unconfirmed
            with pytest.raises(Refused) as refused:
                # uav-a waits one query timeout for uav-b's listing before it refuses
                await fed_c.create_stream(
                    "uav-a", ["heli-altitude"], to_units=["uav-b"], timeout=WAIT
                )
            under_way = "uav-b" in gdf.platforms and "uav-b" not in gdf.unconfirmed
            assert under_way, "uav-b's first snapshot no longer asked: nothing tested"
            assert refused.value.message is not None
            reason = refused.value.message.content
            assert isinstance(reason, str) and reason.startswith("unknown receiver uav-b"), reason
            # present, its snapshot still asked: the requester is told it may ask again
            assert "uav-b not listed here yet" in reason and "ask again" in reason, reason
            assert fed_a.refusals.get("unlisted-receiver") == 1, fed_a.refusals
            records = [
                r for r in _audit(a, "federation", "uav-c") if r.get("code") == "unlisted-receiver"
            ]
            assert len(records) == 1, records
            assert records[0]["verdict"] == "refused"
            assert records[0]["reason"].startswith("unlisted-receiver: unknown receiver uav-b")
            assert fed_a.exports == {} and a.exporter.exports() == []
            token.undeclare()
            silent.undeclare()
            held.clear()
        finally:
            outsider.close()

        # the real uav-b: listed once its signed snapshot answered, then a receiver
        node("uav-b")
        await _until("uav-a lists the real uav-b", lambda: "uav-b" in gdf.listed)
        export_id = await fed_c.create_stream(
            "uav-a", ["heli-altitude"], to_units=["uav-b"], timeout=WAIT
        )
        assert fed_a.exports[export_id].receivers == ["uav-b"]
        assert [(e.receiver, e.semantic_label) for e in a.exporter.exports()] == [
            ("uav-b", "heli-altitude")
        ]
        assert fed_a.refusals.get("unlisted-receiver") == 1, fed_a.refusals


async def test_a_forged_leave_on_mqtt_stops_no_stream(
    tmp_path: Path, mosquitto: tuple[str, int]
) -> None:
    """The issue's attack: uav-b's presence cleared while uav-a streams to it."""
    host, port = mosquitto
    fed = f"member{os.getpid()}s"
    mqtt = f'kind = "mqtt"\nhost = "{host}"\nport = {port}'
    _federation(tmp_path, fed, ["uav-a", "uav-b"], {"uav-a": mqtt, "uav-b": mqtt})
    ended: list[tuple[str, list[str]]] = []  # what uav-b was told of ended imports
    async with (
        asyncio.timeout(4 * WAIT),
        # uav-a (the exporter) leaves first: the import proxy's shutdown while it still
        # reports to a live sender over MQTT can hang (seen before these changes too)
        FederationPlatform(
            PlatformConfig.load(tmp_path / "uav-b.toml"),
            on_import_ended=lambda sender, labels: ended.append((sender, labels)),
        ) as b,
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
    ):
        await _until("both see each other", lambda: "uav-b" in a.members and "uav-a" in b.members)
        altitude = a.instance.add_source("uav-a/alt")
        await b.federation_agent.create_stream("uav-a", ["heli-altitude"], timeout=WAIT)
        altitude.push(100.0)
        label = await b.imported("uav-a", "heli-altitude", timeout=WAIT)
        assert a.exporter.exports("uav-b")
        attacker = paho.Client(paho.CallbackAPIVersion.VERSION2, protocol=paho.MQTTv5)
        attacker.connect(host, port)
        attacker.loop_start()
        try:
            prefix = f"dyknow/{fed}/v1"
            for victim in ("uav-b", "uav-a"):  # the receiver's and the sender's presence
                attacker.publish(
                    f"{prefix}/alive/{victim}", b"", qos=1, retain=True
                ).wait_for_publish(5)
            await _until("uav-a audits the forged leave", lambda: _audit(a, "presence", "uav-b"))
            await _until("uav-b audits the forged leave", lambda: _audit(b, "presence", "uav-a"))
            # the export goes on, and samples keep arriving
            assert a.exporter.exports("uav-b"), "uav-a stopped its export to uav-b"
            altitude.push(200.0)
            await _until(
                "the next sample at uav-b",
                lambda: b.instance.latest(label).samples[0].value == 200.0,
            )
            rec = b.importer.get("uav-a", "heli-altitude")
            assert rec is not None and not rec.ended, "uav-b ended its import from uav-a"
            assert ended == [], "uav-b was told its import from uav-a ended"
            assert "uav-b" in a.members and "uav-a" in b.members
        finally:
            attacker.loop_stop()
            attacker.disconnect()


async def test_a_member_that_talks_is_not_taken_for_gone_while_its_directory_sheds_a_flood(
    tmp_path: Path,
) -> None:
    """An outsider floods uav-b's ``df/uav-b`` so it sheds most directory queries.

    uav-a's rechecks then go unanswered; uav-b's authenticated requests to uav-a prove it
    runs as well, so uav-a keeps it listed (without them it would be taken for gone after
    two intervals, and its streams stopped).
    """
    from bench._flood import FLOOD_SECONDS, START, recv
    from bench.kxflood import attacker_main, go

    fed = f"member{os.getpid()}f"
    port = free_tcp_port()
    _federation(
        tmp_path,
        fed,
        ["uav-a", "uav-b"],
        {
            "uav-a": f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]',
            "uav-b": f'mode = "peer"\nconnect = ["tcp/127.0.0.1:{port}"]',
        },
    )
    ctx = multiprocessing.get_context("spawn")
    here, there = ctx.Pipe()
    key = f"dyknow/{fed}/v1/df/uav-b"
    attacker = ctx.Process(target=attacker_main, args=(f"tcp/127.0.0.1:{port}", key, there))
    attacker.start()
    try:
        async with (
            asyncio.timeout(4 * WAIT + FLOOD_SECONDS),
            FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
            FederationPlatform(PlatformConfig.load(tmp_path / "uav-b.toml")) as b,
        ):
            gdf = a.agents.global_df
            assert gdf is not None and b.agents.df is not None
            await _until("uav-a sees uav-b", lambda: "uav-b" in a.members)
            gdf.recheck_interval = 1.0  # 30 s by default

            async def talk() -> None:  # what a member streaming or asking does anyway
                while True:
                    try:
                        await b.federation_agent.request_from(
                            "uav-a", {"action": "list-labels"}, timeout=2.0
                        )
                    except ReplyTimeout:
                        pass  # the request itself reached uav-a, authenticated: enough
                    await asyncio.sleep(0.3)

            talker = asyncio.create_task(talk(), name="uav-b talks to uav-a")
            try:
                assert await asyncio.to_thread(recv, here, "the attacker", START) == "ready"
                go(here, [b""])
                flooded = time.monotonic()
                while time.monotonic() - flooded < 5.0:  # five recheck intervals
                    assert "uav-b" in gdf.platforms, "uav-b taken for gone during the flood"
                    await asyncio.sleep(0.1)
                shed = b.agents.df.queries_shed
                assert shed > 1000, shed  # the flood was real: uav-a's rechecks went unanswered
                assert "uav-b" in a.members
            finally:
                here.send("stop")
                talker.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await talker
    finally:
        attacker.join(WAIT)
        if attacker.is_alive():
            attacker.kill()
            attacker.join(WAIT)
