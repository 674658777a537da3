"""The reference scenario's federation steps: three platforms, three OS processes.

UAV A and the operator station run in their own (spawned) processes; the test process
hosts UAV B, which drives the scenario and checks it, and ``uav-c``, a platform that
lists a federation service but never answers. Every platform is a `FederationPlatform`
built from a TOML config (keys and one trust file generated into a temporary directory,
one vocabulary, a label mapping per platform with different local labels). Over zenoh
(peers on loopback, explicit endpoints) and over MQTT (the conftest's mosquitto):

a. B's global request for the latest ``heli-max-speed`` and ``heli-altitude``: answers
   from the UAVs, the operator's refusal, ``uav-c`` named as silent;
b. B asks A ``create-stream car5-state sample-period 0.5 to-units uav-b``: B's imported
   stream gets A's samples on the 0.5 s grid of A's valid times;
c. ``get-trajectory car5-state from -120``: the last two minutes of A's samples;
d. B fuses its own car5 state (it sees car5 for a while) with A's, preferring its own;
e. A is SIGKILLed: the operator is told ``gone`` (within 1 s on zenoh), B's imported
   stream ends.

Readiness is by events (membership, the operator's watcher answering when it sees the
others), never fixed sleeps; every wait is bounded; children are killed in ``finally``.
The last tests build platforms in one process (MemoryHub): config errors, imports of
labels never agreed, exports to a platform that is gone.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import multiprocessing
import os
import signal
import time
import uuid
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field
from itertools import pairwise
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

import pytest

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    Failed,
    Failure,
    InterfaceAgent,
    KeyPair,
    MessageTemplate,
    Performative,
    Refused,
    ReplyTimeout,
    ServiceDescription,
    TrustStore,
    UnknownPlatform,
    Visibility,
    on,
    on_request,
    request,
)
from agents.keys import gen_keys, trust_keys
from agents.transports import (
    MemoryHub,
    MqttConfig,
    MqttTransport,
    Subscription,
    Transport,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
)
from dyknow_core import NS_PER_S, DyKnowInstance, Policy, Sample, Source
from dyknow_core import Subscription as StreamSubscription
from federation import (
    FEDERATION_SERVICE_TYPE,
    ONTOLOGY,
    FederationPlatform,
    MembershipEvent,
    PlatformConfig,
    PlatformConfigError,
    SharingSettings,
)
from ontology import StreamRule, UnknownSemanticLabel

# every child a test spawned is gone after it, whatever the test did
pytestmark = pytest.mark.usefixtures("no_leftover_children")

START = 30.0  # spawned interpreters import zenoh, pydantic and DyKnow: seconds when loaded
WAIT = 10.0  # the bound on any other single wait
TOTAL = 50.0  # the bound on one transport's whole scenario
PERIOD = 0.5  # the sample period B asks for
WINDOW = 0.25  # the fusion's window: an imported sample this close to a local one yields
HISTORY = 180  # seconds of car5 history A holds when it starts (1 Hz)
A_RATE = 0.1  # A's tracker period, s
B_SEEN = 12  # samples of car5 B's own camera gets (at 10 Hz): then car5 leaves its view
A_MAX_SPEED, A_ALTITUDE = 22.0, 120.0
B_MAX_SPEED, B_ALTITUDE = 18.0, 95.0
P = Performative

VOCABULARY = {
    "name": "traffic",
    "labels": {
        "heli-max-speed": "this platform's top speed, m/s",
        "heli-altitude": "this platform's altitude, m",
        "{object}-state": "the state of a tracked object, e.g. car5-state",
    },
}
# The same semantic labels, different local labels on each platform.
MAPPINGS: dict[str, dict[str, str]] = {
    "uav-a": {
        "heli-max-speed": "heli/max_speed",
        "heli-altitude": "heli/altitude",
        "{object}-state": "cars/{object}/state",
    },
    "uav-b": {
        "heli-max-speed": "platform/limits/speed",
        "heli-altitude": "platform/nav/alt",
        "{object}-state": "tracks/{object}/state",
    },
    "operator": {"{object}-state": "picture/{object}"},
}
PLATFORMS = ["uav-a", "uav-b", "operator"]
SILENT = "uav-c"


# -- files -------------------------------------------------------------------------------------


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string for what these tests write
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"no TOML for {value!r}")


def write_toml(path: Path, data: dict[str, Any]) -> Path:
    """``data`` as TOML: top-level values, then one table per dict value."""
    lines = [
        f"{json.dumps(k)} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, dict)
    ]
    for table, content in data.items():
        if isinstance(content, dict):
            lines.append(f"\n[{table}]")
            lines += [f"{json.dumps(k)} = {_toml_value(v)}" for k, v in content.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_federation(
    tmp_path: Path, federation: str, transports: dict[str, dict[str, Any]]
) -> dict[str, Path]:
    """Keys, one trust file, the vocabulary, mappings and a config file per platform."""
    keys = tmp_path / "keys"
    pubs = [gen_keys(name, keys)[2] for name in [*PLATFORMS, SILENT]]
    trust_keys(tmp_path / "trust.json", pubs, federation=federation)
    write_toml(tmp_path / "traffic.toml", VOCABULARY)
    configs = {}
    for name in PLATFORMS:
        write_toml(
            tmp_path / f"{name}-labels.toml", {"vocabulary": "traffic", "labels": MAPPINGS[name]}
        )
        configs[name] = write_toml(
            tmp_path / f"{name}.toml",
            {
                "name": name,
                "federation": federation,
                "key": f"keys/{name}.key",  # relative to the config file
                "trust": "trust.json",
                "vocabulary": "traffic.toml",
                "mapping": f"{name}-labels.toml",
                "export_limit": 8,
                "transport": transports[name],
            },
        )
    return configs


# -- the child processes -----------------------------------------------------------------------


def child_main(role: str, config_path: str) -> None:
    """A child platform (``uav-a`` or ``operator``) until it is killed."""
    main = _uav_a if role == "uav-a" else _operator
    asyncio.run(main(PlatformConfig.load(config_path)))


def car_state(k: int, t: int, by: str) -> dict[str, Any]:
    """A tracked car's state as a UAV's tracker publishes it (``t``: its valid time, ns)."""
    return {"k": k, "t": t, "by": by, "x": 100.0 + k, "y": 5.0}


async def _uav_a(config: PlatformConfig) -> None:
    async with FederationPlatform(config, join=False) as p:
        dk = p.instance
        dk.add_source("heli/max_speed").push(A_MAX_SPEED)
        dk.add_source("heli/altitude").push(A_ALTITUDE)
        car5 = dk.add_source("cars/car5/state")
        now = dk.clock.now()
        # A has tracked car5 for a while already: one state a second
        car5.push_batch(
            [
                (car_state(k, tv, "uav-a"), tv, now + k)
                for k in range(HISTORY)
                for tv in [now - (HISTORY - k) * NS_PER_S]
            ]
        )
        await p.join()
        k = HISTORY
        while True:  # the tracker, until the parent kills us
            await asyncio.sleep(A_RATE)
            t = dk.clock.now()
            car5.push(car_state(k, t, "uav-a"), t)
            k += 1


class Watcher(Agent):
    """The operator's view of membership, recorded with monotonic times (instrumentation).

    ``{"members": [p…]}`` is answered once this platform sees them all as members,
    ``{"gone": p}`` once it was told p is gone; both with the members and every event.
    """

    def __init__(self, platform: FederationPlatform) -> None:
        super().__init__("watcher")
        self.fp = platform
        self.events: list[tuple[str, str, float]] = []
        self.changed = asyncio.Event()

    async def setup(self) -> None:
        """Protected: the driver on uav-b reaches it through the Interface Agent."""
        assert self.platform.df is not None
        await self.platform.df.register(
            ServiceDescription(
                name="watcher", type="scenario-watcher", provider=self.aid, visibility="protected"
            )
        )
        self.spawn(self._follow(self.fp.membership()), "follow")

    async def _follow(self, events: Subscription[MembershipEvent]) -> None:
        async with events:
            async for e in events:
                self.events.append((e.kind, e.platform, time.monotonic()))
                self.changed.set()

    def _reached(self, want: dict[str, Any]) -> bool:
        if "members" in want:
            return set(want["members"]) <= set(self.fp.members)
        return any(k == "gone" and p == want["gone"] for k, p, _ in self.events)

    @on_request("watcher", concurrent=True)
    async def _until(self, message: ACLMessage) -> Any:
        """Answer when what the content asks for has happened (at most ``timeout`` s)."""
        want = message.content
        assert isinstance(want, dict)
        async with asyncio.timeout(float(want.get("timeout", WAIT))):
            while not self._reached(want):
                self.changed.clear()
                await self.changed.wait()
        return {"members": self.fp.members, "events": [list(e) for e in self.events]}


async def _operator(config: PlatformConfig) -> None:
    async with FederationPlatform(config, join=False) as p:
        await p.agents.add(Watcher(p))
        await p.join()
        await asyncio.Event().wait()  # until the parent kills us


# -- the parent: uav-b and the silent uav-c ------------------------------------------------------


class Silent(Agent):
    """Lists a federation service but never answers: a platform too busy to reply."""

    def __init__(self) -> None:
        super().__init__("federation")

    async def setup(self) -> None:
        """Only the public discovery entry: enough to be asked by global requests."""
        assert self.platform.df is not None
        await self.platform.df.register(
            ServiceDescription(
                name="dyknow-federation-discovery",
                type=FEDERATION_SERVICE_TYPE,
                provider=self.aid,
                visibility=Visibility.PUBLIC,
            )
        )

    @on(MessageTemplate((P.REQUEST, P.QUERY_REF), ontology=ONTOLOGY))
    async def _swallow(self, message: ACLMessage) -> None:
        """Say nothing."""


@contextlib.contextmanager
def children_watched(procs: dict[str, BaseProcess]) -> Iterator[asyncio.Future[str]]:
    """A future done (with the child's name) as soon as any child process exits."""
    loop = asyncio.get_running_loop()
    died: asyncio.Future[str] = loop.create_future()

    def exited(name: str) -> None:
        if not died.done():
            died.set_result(name)

    sentinels = []
    for name, proc in procs.items():
        loop.add_reader(proc.sentinel, exited, name)
        sentinels.append(proc.sentinel)
    try:
        yield died
    finally:
        for s in sentinels:
            loop.remove_reader(s)


async def until_members(
    b: FederationPlatform,
    events: Subscription[MembershipEvent],
    want: set[str],
    died: asyncio.Future[str],
) -> None:
    """Wait (by membership events) until B sees ``want``; fail at once if a child died."""
    async with asyncio.timeout(START):
        while not want <= set(b.members):
            get = asyncio.ensure_future(events.get())
            try:
                await asyncio.wait([get, died], return_when=asyncio.FIRST_COMPLETED)
                if died.done():
                    raise AssertionError(f"{died.result()} exited before the federation was up")
            finally:
                get.cancel()


async def next_event(events: Subscription[MembershipEvent], want: MembershipEvent) -> None:
    """Read ``events`` until ``want`` (the caller bounds the wait)."""
    while await events.get() != want:
        pass


async def ask_watcher(driver: Agent, content: dict[str, Any]) -> dict[str, Any]:
    """What the operator's watcher answers (it waits for what ``content`` asks)."""
    timeout = float(content.get("timeout", WAIT))
    answer = await request(
        driver, "watcher@operator", content, ontology="watcher", timeout=timeout + 2
    )
    assert isinstance(answer, dict)
    return answer


@dataclass
class Scene:
    """UAV B (this process) and what the steps share."""

    b: FederationPlatform
    driver: Agent
    events: Subscription[MembershipEvent]
    procs: dict[str, BaseProcess]
    ended: asyncio.Future[tuple[str, list[str]]]
    deadline: float  # of the global request: the silent platform holds it this long
    sources: dict[str, Source]  # B's own, by local label
    timings: dict[str, float] = field(default_factory=dict)
    imports: StreamSubscription | None = None  # B's subscription to A's car5 states

    @property
    def dk(self) -> DyKnowInstance:
        return self.b.instance


async def step_global_request(scene: Scene) -> None:
    """(a) The latest heli-max-speed and heli-altitude of every member."""
    b = scene.b
    scene.sources["platform/limits/speed"].push(B_MAX_SPEED)
    scene.sources["platform/nav/alt"].push(B_ALTITUDE)
    result = await b.federation_agent.global_request(
        {"action": "get-latest", "labels": ["heli-max-speed", "heli-altitude"]},
        deadline=scene.deadline,
        select="newest",
        include_self=True,
    )
    assert sorted(result.asked) == sorted([*PLATFORMS, SILENT])
    assert sorted(result.answers) == ["uav-a", "uav-b"]  # the UAVs
    answers: Any = result.answers
    for platform, values in (
        ("uav-a", [A_MAX_SPEED, A_ALTITUDE]),
        ("uav-b", [B_MAX_SPEED, B_ALTITUDE]),
    ):
        latest = [
            answers[platform][s]["samples"][0][0] for s in ("heli-max-speed", "heli-altitude")
        ]
        assert latest == values, platform
    assert list(result.refused) == ["operator"]  # it maps no heli-* label
    assert "heli-max-speed" in result.refused["operator"]
    assert "heli/" not in json.dumps(answers)  # local labels stay home
    assert result.no_answer == [SILENT]
    assert result.chosen == "uav-b"  # its values were pushed last: the newest
    assert result.value == answers["uav-b"]


async def step_trajectory(scene: Scene) -> None:
    """(c) get-trajectory car5-state from -120: the last two minutes of A's samples."""
    answer = await scene.b.federation_agent.request_from(
        "uav-a",
        {"action": "get-trajectory", "labels": ["car5-state"], "from": -120, "relative": True},
        timeout=WAIT,
    )
    query_time = answer["car5-state"]["query_time"]
    rows = answer["car5-state"]["samples"]
    ks = [value["k"] for value, _, _ in rows]
    assert ks == list(range(ks[0], ks[0] + len(ks))), "A's samples, none missing"
    assert 0 < ks[0] < HISTORY < ks[-1]  # older history left out, the live ones in
    first_tv, last_tv = rows[0][1], rows[-1][1]
    assert query_time - 120 <= first_tv < query_time - 119  # the one before it: out
    assert query_time - 1 < last_tv <= query_time
    assert all(abs(tv - value["t"] / NS_PER_S) < 1e-6 for value, tv, _ in rows)
    assert all(value["by"] == "uav-a" for value, _, _ in rows)


async def step_stream_and_fusion(scene: Scene) -> None:
    """(b) create-stream to B, (c) meanwhile, (d) fusion preferring B's own car5 states."""
    b, dk = scene.b, scene.dk
    t = time.monotonic()
    export_id = await b.federation_agent.create_stream(
        "uav-a", ["car5-state"], sample_period=PERIOD, to_units=["uav-b"], timeout=WAIT
    )
    assert export_id.startswith("x-")
    label = b.import_label("uav-a", "car5-state")
    assert label == "import/uav-a/car5-state"
    assert await b.imported("uav-a", "car5-state", timeout=WAIT) == label
    scene.timings["first-import"] = time.monotonic() - t
    # Nothing suspends between these three lines: the fusion and the subscription see
    # the same imported samples, those that arrived already included (the fusion's too).
    # What the fusion emits as it starts is read too: on a loaded machine an import can
    # come later than its window, and its replay emits it at once.
    imports = dk.subscribe(label, Policy(start=0))
    fusion = await b.fuse("car5-state", "uav-a", "fused/car5/state", window=WINDOW)
    fused = dk.subscribe("fused/car5/state", Policy(start=0))

    await step_trajectory(scene)

    # A's samples come; then B's camera sees car5 for a while; then only A does again.
    async with asyncio.timeout(WAIT):
        got: list[Sample] = [await imports.get() for _ in range(2)]
    camera = scene.sources["tracks/car5/state"]
    local: list[Sample] = []
    for i in range(B_SEEN):
        tv = dk.clock.now()
        camera.push(car_state(i, tv, "uav-b"), tv)
        local.append(dk.latest("tracks/car5/state").samples[0])
        await asyncio.sleep(0.1)  # the camera's rate: the scenario, not a wait for readiness
    after = local[-1].valid_time + round((WINDOW + PERIOD) * NS_PER_S)
    out: list[Sample] = []
    async with asyncio.timeout(WAIT):
        # until the fusion emitted one of A's samples well after B's last
        while not out or out[-1].value["by"] != "uav-a" or out[-1].valid_time <= after:
            out.append(await fused.get())
        while got[-1].valid_time < out[-1].valid_time:
            got.append(await imports.get())
    scene.timings["stream-and-fusion"] = time.monotonic() - t

    # (b) A's samples on the 0.5 s grid, with A's valid times, nothing lost
    period = round(PERIOD * NS_PER_S)
    assert all(s.valid_time % period == 0 for s in got), "on the grid"
    # one per period (a period in which A's tracker published nothing would have none)
    assert all(y.valid_time > x.valid_time for x, y in pairwise(got)), "one per period"
    for s in got:
        assert s.value["by"] == "uav-a"
        assert s.valid_time - period < s.value["t"] <= s.valid_time  # A's sample of that period
        assert s.available_time >= s.valid_time  # available here after the fact
    rec = b.importer.get("uav-a", "car5-state")
    assert rec is not None and rec.local_label == label and rec.lost == 0

    # (d) B's samples where it has them, A's elsewhere
    w = WINDOW * NS_PER_S
    near = [s for s in got if any(abs(s.valid_time - x.valid_time) <= w for x in local)]
    expected_a = [s.valid_time for s in got if s not in near]
    fused_b = [s.valid_time for s in out if s.value["by"] == "uav-b"]
    fused_a = sorted(s.valid_time for s in out if s.value["by"] == "uav-a")
    assert fused_b == [x.valid_time for x in local]
    assert fused_a == expected_a
    assert near and fusion.suppressed == len(near), "B's own samples won where it had some"
    assert expected_a[0] < local[0].valid_time and expected_a[-1] > local[-1].valid_time

    scene.imports = imports


async def step_kill_a(scene: Scene, gone_within: float) -> None:
    """(e) A is SIGKILLed: B and the operator are told, B's imported stream ends."""
    b, imports = scene.b, scene.imports
    pid = scene.procs["uav-a"].pid
    assert pid is not None and imports is not None
    killed = time.monotonic()
    os.kill(pid, signal.SIGKILL)
    async with asyncio.timeout(gone_within):
        await next_event(scene.events, MembershipEvent("gone", "uav-a"))
        assert await scene.ended == ("uav-a", ["car5-state"])
        async for _ in imports:  # the subscription to the import ends
            pass
    scene.timings["b-told"] = time.monotonic() - killed
    rec = b.importer.get("uav-a", "car5-state")
    assert rec is not None and rec.ended
    report = await ask_watcher(scene.driver, {"gone": "uav-a"})
    told = [at for k, p, at in report["events"] if (k, p) == ("gone", "uav-a")]
    scene.timings["operator-told"] = told[0] - killed
    assert 0 <= told[0] - killed < gone_within, scene.timings
    assert "uav-a" not in report["members"] and "uav-a" not in b.members


async def _scenario(
    kind: str,
    tmp_path: Path,
    transports: dict[str, dict[str, Any]],
    silent_transport: Transport,
    gone_within: float,
    deadline: float,
) -> dict[str, float]:
    """Run the scenario; how long its steps took (s)."""
    federation = f"scn-{uuid.uuid4().hex[:8]}"
    configs = write_federation(tmp_path, federation, transports)
    ctx = multiprocessing.get_context("spawn")
    procs: dict[str, BaseProcess] = {
        role: ctx.Process(
            target=child_main, args=(role, str(configs[role])), name=f"scenario-{kind}-{role}"
        )
        for role in ("uav-a", "operator")
    }
    ended: asyncio.Future[tuple[str, list[str]]] = asyncio.get_running_loop().create_future()

    def import_ended(sender: str, labels: list[str]) -> None:
        if not ended.done():
            ended.set_result((sender, labels))

    silent_channel = InterfaceAgent(
        KeyPair.load(tmp_path / "keys" / f"{SILENT}.key"),
        TrustStore.load(tmp_path / "trust.json"),
        publish_audit=False,
    )
    try:
        async with (
            asyncio.timeout(TOTAL),
            FederationPlatform.from_file(
                configs["uav-b"], join=False, on_import_ended=import_ended
            ) as b,
            silent_transport,
            AgentPlatform(
                SILENT, silent_transport, federation=federation, channel=silent_channel
            ) as silent,
        ):
            sources = {
                local: b.instance.add_source(local)
                for local in ("platform/limits/speed", "platform/nav/alt", "tracks/car5/state")
            }
            driver = await b.agents.add(Agent("driver"))
            await b.join()
            await silent.add(Silent())
            async with b.membership() as events:
                scene = Scene(b, driver, events, procs, ended, deadline, sources)
                started = time.monotonic()
                for proc in procs.values():
                    proc.start()
                with children_watched(procs) as died:
                    await until_members(b, events, {*PLATFORMS, SILENT}, died)
                    # The operator must see A itself: it is to be told when A goes.
                    seen, provided = await asyncio.gather(
                        ask_watcher(driver, {"members": PLATFORMS, "timeout": START}),
                        b.federation_agent.request_from(
                            "uav-a", {"action": "list-labels"}, timeout=WAIT
                        ),
                    )
                    assert set(PLATFORMS) <= set(seen["members"])
                    assert provided == {"labels": ["car5-state", "heli-altitude", "heli-max-speed"]}
                    scene.timings["ready"] = time.monotonic() - started
                t = time.monotonic()
                await step_global_request(scene)
                scene.timings["global-request"] = time.monotonic() - t
                await step_stream_and_fusion(scene)
                await step_kill_a(scene, gone_within)
    finally:
        for proc in procs.values():
            if proc.pid is None:
                continue  # never started
            if proc.is_alive():
                proc.kill()
            proc.join(timeout=10)
    print(f"{kind}: " + ", ".join(f"{k} {v:.2f} s" for k, v in scene.timings.items()))
    return scene.timings


async def test_scenario_over_zenoh(tmp_path: Path) -> None:
    ports = {name: free_tcp_port() for name in [*PLATFORMS, SILENT]}
    seed = f"tcp/127.0.0.1:{ports['uav-b']}"

    def peer(name: str) -> dict[str, Any]:
        connect = [] if name == "uav-b" else [seed]  # the others find each other by gossip
        return {
            "kind": "zenoh",
            "mode": "peer",
            "listen": [f"tcp/127.0.0.1:{ports[name]}"],
            "connect": connect,
        }

    silent = ZenohTransport(ZenohConfig.loopback(ports[SILENT], connect=[ports["uav-b"]]))
    await _scenario(
        "zenoh", tmp_path, {n: peer(n) for n in PLATFORMS}, silent, gone_within=1.0, deadline=1.5
    )


async def test_scenario_over_mqtt(mosquitto: tuple[str, int], tmp_path: Path) -> None:
    host, port = mosquitto
    broker = {"kind": "mqtt", "host": host, "port": port, "keepalive": 2}
    silent = MqttTransport(MqttConfig(host=host, port=port, keepalive=2))
    # A killed client's connection closes at once; the keepalive (1.5 x 2 s) bounds the rest.
    # A first contact's key exchange ends at its first authenticated reply, as on zenoh;
    # the broker's hop makes the global request's deadline a little longer than zenoh's.
    await _scenario(
        "mqtt", tmp_path, {n: broker for n in PLATFORMS}, silent, gone_within=4.0, deadline=2.0
    )


# -- one process: the assembly itself --------------------------------------------------------------


def _config(tmp_path: Path, name: str, federation: str = "demo", **more: Any) -> dict[str, Any]:
    return {
        "name": name,
        "federation": federation,
        "key": str(tmp_path / "keys" / f"{name}.key"),
        "trust": str(tmp_path / "trust.json"),
        "vocabulary": VOCABULARY,
        "mapping": {"labels": MAPPINGS[name]},
        **more,
    }


@pytest.fixture
def demo_keys(tmp_path: Path) -> Path:
    pubs = [gen_keys(name, tmp_path / "keys")[2] for name in PLATFORMS]
    trust_keys(tmp_path / "trust.json", pubs, federation="demo")
    return tmp_path


def test_config_errors_name_the_key(demo_keys: Path) -> None:
    tmp_path = demo_keys
    good = _config(tmp_path, "uav-a")
    cases = {
        "name": {**good, "name": "uav a"},
        "transport.listen": {**good, "transport": {"listen": ["nowhere"]}},
        "transport.kind": {**good, "transport": {"kind": "carrier-pigeon"}},
        "transport.port": {**good, "transport": {"kind": "mqtt", "port": 0}},
        "import_label": {**good, "import_label": "import/{semantic}"},
        "export_limit": {**good, "export_limit": -1},
        "colour": {**good, "colour": "blue"},
    }
    for key, data in cases.items():
        with pytest.raises(PlatformConfigError) as info:
            PlatformConfig.from_dict(data, source="uav-a.toml")
        assert info.value.key == key, str(info.value)
        assert str(info.value).startswith(f"uav-a.toml: {key}: ")
    with pytest.raises(PlatformConfigError, match=r"^uav-a.toml: key: missing"):
        PlatformConfig.from_dict({k: v for k, v in good.items() if k != "key"}, source="uav-a.toml")

    # Files are read when the platform is built: the error names the key that is wrong.
    wrong_key = PlatformConfig.from_dict({**good, "key": str(tmp_path / "keys" / "uav-b.key")})
    with pytest.raises(PlatformConfigError, match=r"key: .* is the key of 'uav-b', not of 'uav-a'"):
        FederationPlatform(wrong_key)
    other_fed = PlatformConfig.from_dict({**good, "federation": "other"})
    with pytest.raises(PlatformConfigError, match=r"trust: .* federation 'demo', not of 'other'"):
        FederationPlatform(other_fed)
    bad_mapping = PlatformConfig.from_dict({**good, "mapping": {"labels": {"weather": "w"}}})
    with pytest.raises(PlatformConfigError, match=r"mapping: .*weather.*not in the vocabulary"):
        FederationPlatform(bad_mapping)

    # A TOML file: paths relative to it; errors name the file.
    write_toml(tmp_path / "traffic.toml", VOCABULARY)
    write_toml(tmp_path / "uav-a-labels.toml", {"labels": MAPPINGS["uav-a"]})
    path = write_toml(
        tmp_path / "uav-a.toml",
        {**good, "key": "keys/uav-a.key", "trust": "trust.json", "vocabulary": "traffic.toml",
         "mapping": "uav-a-labels.toml", "transport": {"kind": "mqtt", "port": 1884}},
    )  # fmt: skip
    config = PlatformConfig.load(path)
    assert (
        config.key == tmp_path / "keys" / "uav-a.key"
        and config.mapping == tmp_path / "uav-a-labels.toml"
    )
    assert config.transport.kind == "mqtt" and config.import_label == "import/{sender}/{semantic}"
    platform = FederationPlatform(config)
    assert platform.labels.to_local("car5-state") == "cars/car5/state"
    assert platform.import_label("uav-b", "car5-state") == "import/uav-b/car5-state"
    with pytest.raises(UnknownSemanticLabel):
        platform.import_label("uav-b", "weather")
    (tmp_path / "broken.toml").write_text("name = \n")
    with pytest.raises(PlatformConfigError, match=r"broken.toml: not valid TOML"):
        PlatformConfig.load(tmp_path / "broken.toml")


@contextlib.asynccontextmanager
async def memory_federation(
    tmp_path: Path, **options: Any
) -> AsyncIterator[tuple[dict[str, FederationPlatform], contextlib.AsyncExitStack]]:
    """The three platforms on one MemoryHub, members of each other; uav-b on its own stack."""
    hub = MemoryHub()
    async with contextlib.AsyncExitStack() as stack, contextlib.AsyncExitStack() as b_stack:
        async with asyncio.timeout(WAIT):
            platforms = {}
            for name in PLATFORMS:
                owner = b_stack if name == "uav-b" else stack
                t = await owner.enter_async_context(hub.transport())
                config = PlatformConfig.from_dict(_config(tmp_path, name, **options))
                platforms[name] = await owner.enter_async_context(
                    FederationPlatform(config, transport=t)
                )
            for p in platforms.values():
                async with p.membership() as events:
                    while sorted(p.members) != sorted(PLATFORMS):
                        await events.get()
            yield platforms, b_stack


async def test_in_one_process_imports_and_exports_to_a_gone_platform_stop(demo_keys: Path) -> None:
    async with memory_federation(demo_keys, import_label="from/{sender}/{semantic}") as (
        ps,
        b_stack,
    ):
        a, b = ps["uav-a"], ps["uav-b"]
        car5 = a.instance.add_source("cars/car5/state")
        export_id = await b.federation_agent.create_stream("uav-a", ["car5-state"], timeout=WAIT)
        car5.push(car_state(0, 1, "uav-a"), 1)
        label = await b.imported("uav-a", "car5-state", timeout=WAIT)
        assert label == "from/uav-a/car5-state" == b.import_label("uav-a", "car5-state")
        assert b.instance.latest(label).samples[0].value == car_state(0, 1, "uav-a")
        assert b.instance.stream(label).location == "import/uav-a"
        # what the vocabulary does not have is never injected
        wind = a.instance.add_source("weather/wind")
        stray = a.exporter.start_exporting("weather/wind", "wind", "uav-b")
        wind.push(4.2)
        async with asyncio.timeout(WAIT):
            while not b.importer.stats()["totals"]["dropped_samples"].get("unagreed"):  # noqa: ASYNC110
                await asyncio.sleep(0.005)  # the proxy's counters have no event to await
        assert not b.instance.has_label("from/uav-a/wind")
        await a.exporter.stop(stray)

        # uav-b goes: A stops exporting to it, through the export proxy
        assert [e.receiver for e in a.exporter.exports()] == ["uav-b"]
        async with a.membership() as events:
            await b_stack.aclose()
            async with asyncio.timeout(WAIT):
                await next_event(events, MembershipEvent("gone", "uav-b"))
        assert a.exporter.exports() == [] and export_id not in a.federation_agent.exports


async def test_rules_see_the_streams_added_after_the_platform_is_entered(demo_keys: Path) -> None:
    """docs/federation.md's pattern: enter with join=False, add the application's streams,
    join. Label search by formula finds them, and a stream added later still."""
    hub = MemoryHub()
    rules = [StreamRule("cars/{object}/color", "Color")]
    async with contextlib.AsyncExitStack() as stack, asyncio.timeout(WAIT):
        a = await stack.enter_async_context(
            FederationPlatform(
                PlatformConfig.from_dict(_config(demo_keys, "uav-a")),
                transport=await stack.enter_async_context(hub.transport()),
                join=False,
                rules=rules,
            )
        )
        b = await stack.enter_async_context(
            FederationPlatform(
                PlatformConfig.from_dict(_config(demo_keys, "uav-b")),
                transport=await stack.enter_async_context(hub.transport()),
            )
        )
        a.instance.add_source("cars/car5/state").push(car_state(0, 1, "uav-a"))
        a.instance.add_source("cars/car5/color").push("blue")
        async with b.membership() as events:
            await a.join()
            while "uav-a" not in b.members:
                await events.get()

        async def search(formula: str) -> Any:
            return await b.federation_agent.request_from(
                "uav-a", {"action": "search-labels", "formula": formula}, timeout=WAIT
            )

        assert await search("(all ?x (Color ?x blue))") == {"labels": ["car5-state"]}
        a.instance.add_source("cars/car7/state").push(car_state(0, 1, "uav-a"))
        car7 = a.instance.add_source("cars/car7/color")
        assert await search("(all ?x (Color ?x red))") == {"labels": []}
        car7.push("red")
        assert await search("(all ?x (Color ?x red))") == {"labels": ["car7-state"]}
        a.instance.remove_process("source:cars/car7/color")  # its facts go with it
        assert await search("(all ?x (Color ?x red))") == {"labels": []}


async def test_config_facts_answer_label_search(demo_keys: Path) -> None:
    """A config-only node's ``[[facts]]`` tables are its rules: label search by formula
    answers from them (a dict value's ``field``, a ``unary`` fact)."""
    hub = MemoryHub()
    facts = [
        {"predicate": "Car", "stream": "cars/{object}/state", "unary": True},
        {"predicate": "Color", "stream": "cars/{object}/state", "field": "colour"},
    ]
    async with contextlib.AsyncExitStack() as stack, asyncio.timeout(WAIT):
        a = await stack.enter_async_context(
            FederationPlatform(
                PlatformConfig.from_dict(_config(demo_keys, "uav-a", facts=facts)),
                transport=await stack.enter_async_context(hub.transport()),
                join=False,
            )
        )
        a.instance.add_source("cars/car5/state").push({"x": 1.0, "colour": "blue"})
        car6 = a.instance.add_source("cars/car6/state")
        car6.push({"x": 2.0, "colour": "red"})
        search = a.labels.find
        assert search("(all ?x (and (Car ?x) (Color ?x blue)))") == ["car5-state"]
        assert search("(all ?x (Color ?x red))") == ["car6-state"]
        car6.push({"x": 3.0})  # no colour: its Color fact is retracted
        assert search("(all ?x (Color ?x red))") == []
        assert search("(all ?x (Car ?x))") == ["car5-state", "car6-state"]


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ({"predicate": "Car"}, "facts[0].stream: missing"),
        ({"predicate": "Car", "stream": "cars/{id}/state"}, "{object}"),
        ({"predicate": "(Car", "stream": "c/{object}"}, "not an SL word"),
        ({"predicate": "Car", "stream": "c/{object}", "field": "a", "unary": True}, "exclude"),
        ({"predicate": "Car", "stream": "c/{object}", "domain": "cars"}, "unknown key"),
    ],
)
def test_config_facts_refused_naming_the_table(
    demo_keys: Path, table: dict[str, Any], message: str
) -> None:
    with pytest.raises(PlatformConfigError, match="facts") as caught:
        PlatformConfig.from_dict(_config(demo_keys, "uav-a", facts=[table]), source="a.toml")
    assert message in str(caught.value)


async def test_an_export_that_ended_by_itself_frees_its_slot(demo_keys: Path) -> None:
    # regression: the agent kept the record of an export whose `to` had passed, so the same
    # request was refused for ever and the export limit filled up
    async with memory_federation(demo_keys) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        car5 = a.instance.add_source("cars/car5/state")
        await b.federation_agent.create_stream(
            "uav-a", ["car5-state"], end=0.2, relative=True, timeout=WAIT
        )
        car5.push(car_state(0, 1, "uav-a"))
        async with asyncio.timeout(WAIT):
            while a.exporter.exports():
                car5.push(car_state(0, 2, "uav-a"))  # a sample past `to` ends the export
                await asyncio.sleep(0.05)
        assert a.federation_agent.export_count == 0
        await b.federation_agent.create_stream("uav-a", ["car5-state"], timeout=WAIT)


async def test_a_durable_stream_for_a_consenting_third_platform_is_asked_again(
    demo_keys: Path,
) -> None:
    # the operator asks uav-a for car5-state to uav-b, which lets the operator do so; when
    # uav-a comes back without the export, the operator asks again, uav-a asks uav-b again
    # and uav-b's import, still agreed, goes on
    consent = {"sharing": {"accept_for": ["operator"]}}
    async with memory_federation(demo_keys, **consent) as (ps, _):
        a, b, op = ps["uav-a"], ps["uav-b"], ps["operator"]
        car5 = a.instance.add_source("cars/car5/state")
        first = await op.federation_agent.create_stream(
            "uav-a", ["car5-state"], to_units=["uav-b"], durable=True, timeout=WAIT
        )
        assert op.importer.get("uav-a", "car5-state") is None  # not for the operator
        car5.push(car_state(0, 1, "uav-a"))
        label = await b.imported("uav-a", "car5-state", timeout=WAIT)
        async with op.membership() as seen:
            await a.leave()
            await next_event(seen, MembershipEvent("left", "uav-a"))
            fed = a.federation_agent
            await fed._end(fed.exports[first])  # as after a restart: its export is gone
            await a.join()
            await next_event(seen, MembershipEvent("joined", "uav-a"))
        async with asyncio.timeout(WAIT):
            while not a.exporter.exports("uav-b"):  # noqa: ASYNC110
                await asyncio.sleep(0.01)  # asked again by itself: no event here
        (again,) = a.federation_agent.exports.values()
        assert again.id != first and again.receivers == ["uav-b"]
        car5.push(car_state(0, 2, "uav-a"))
        async with asyncio.timeout(WAIT):
            while len(b.instance.between(label, 0, 2**62).samples) < 2:
                car5.push(car_state(0, 3, "uav-a"))
                await asyncio.sleep(0.05)
        assert b.federation_agent.refusals == {} and a.federation_agent.refusals == {}


_CONSENT = {"sharing": {"accept_for": ["operator"]}}


async def _directed_to_uav_b(ps: dict[str, FederationPlatform]) -> None:
    """The operator directs two of uav-a's streams to uav-b (by uav-b's consent): car5's
    flowing, car7's agreed and leased (nothing pushed yet)."""
    a, b, op = ps["uav-a"], ps["uav-b"], ps["operator"]
    car5 = a.instance.add_source("cars/car5/state")
    await op.federation_agent.create_stream(
        "uav-a", ["car5-state"], to_units=["uav-b"], timeout=WAIT
    )
    car5.push(car_state(0, 1, "uav-a"))
    await b.imported("uav-a", "car5-state", timeout=WAIT)  # flowing
    a.instance.add_source("cars/car7/state")  # nothing pushed: no batch
    await op.federation_agent.create_stream(
        "uav-a", ["car7-state"], to_units=["uav-b"], timeout=WAIT
    )
    assert b.agreed("uav-a", "car7-state")  # leased: no batch yet


async def test_a_narrowed_accept_for_withdraws_the_streams_agreed_for_those_it_refuses(
    demo_keys: Path,
) -> None:
    # uav-b let the operator direct streams to it, then reloads a [sharing] that lets no one:
    # what the operator directed there, flowing or waiting, is withdrawn, audited
    async with memory_federation(demo_keys, **_CONSENT) as (ps, _):
        b = ps["uav-b"]
        await _directed_to_uav_b(ps)
        await b.reload_sharing(SharingSettings())  # accept_for: nobody
        assert not b.agreed("uav-a", "car5-state") and not b.agreed("uav-a", "car7-state")
        assert b._leased == {} and b._consented == {}
        ended = [r for r in b.interface.audit.records if r.get("code") == "accept-for"]
        assert sorted(r["stream"] for r in ended) == ["car5-state", "car7-state"], ended
        assert all(r["verdict"] == "ended" and r["requester"] == "operator" for r in ended)
        assert all(r["from"] == "uav-a" and r["stage"] == "policy" for r in ended)


async def test_a_withdrawn_stream_ends_at_its_provider_with_its_lease(demo_keys: Path) -> None:
    # the provider is sent nothing at a withdrawal (no message names an export to a
    # receiver that did not ask for it): uav-b reports on it no more, so uav-a's export
    # ends once its lease runs out, and only then
    async with memory_federation(demo_keys, export_lease=2.0, **_CONSENT) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        await _directed_to_uav_b(ps)
        assert sorted(e.semantic_label for e in a.exporter.exports("uav-b")) == [
            "car5-state",
            "car7-state",
        ]
        await b.reload_sharing(SharingSettings())  # accept_for: nobody
        async with asyncio.timeout(WAIT):
            while a.exporter.exports("uav-b"):  # noqa: ASYNC110
                await asyncio.sleep(0.05)  # the lease's end: no event to await
        ended = {e.semantic_label: e.ended for e in a.exporter.ended if e.receiver == "uav-b"}
        assert sorted(ended) == ["car5-state", "car7-state"], ended
        assert all(
            str(why).startswith("lease-expired: no report from uav-b") for why in ended.values()
        )


async def test_the_streams_a_revoked_platform_directed_here_are_withdrawn(
    demo_keys: Path,
) -> None:
    # the operator directed two of uav-a's streams to uav-b (by uav-b's consent), then uav-b
    # revokes the operator: both are withdrawn, audited
    async with memory_federation(demo_keys, **_CONSENT) as (ps, _):
        b = ps["uav-b"]
        await _directed_to_uav_b(ps)
        assert b.interface.trust.remove("operator")
        async with asyncio.timeout(WAIT):
            while b.agreed("uav-a", "car5-state") or b.agreed("uav-a", "car7-state"):  # noqa: ASYNC110
                await asyncio.sleep(0.01)  # the revocation's task: no event to await
        assert b._consented == {}
        ended = [
            r
            for r in b.interface.audit.records
            if r.get("code") == "untrusted" and r.get("requester") == "operator"
        ]
        assert sorted(r["stream"] for r in ended) == ["car5-state", "car7-state"], ended
        assert all(r["verdict"] == "ended" and r["stage"] == "trust" for r in ended)
        assert all(r["from"] == "uav-a" for r in ended)
        assert b.revoked_imports == 2
        # as a narrowed accept_for withdraws: what uav-a sends of them now is dropped here
        before = b.importer.get("uav-a", "car5-state")
        assert before is None or before.ended


async def test_a_global_create_stream_is_received_from_every_provider_that_agreed(
    demo_keys: Path,
) -> None:
    # asked of every member at once: each stream that comes back was asked for, so imported
    async with memory_federation(demo_keys) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        car5 = a.instance.add_source("cars/car5/state")
        result = await b.federation_agent.global_request(
            {"action": "create-stream", "labels": ["car5-state"]}, deadline=WAIT
        )
        assert list(result.answers) == ["uav-a"] and "operator" in result.refused
        car5.push(car_state(0, 1, "uav-a"))
        label = await b.imported("uav-a", "car5-state", timeout=WAIT)
        assert b.instance.latest(label).samples[0].value == car_state(0, 1, "uav-a")
        assert not b.importer.stats()["totals"]["dropped_samples"]
        # the provider that refused leaves nothing agreed behind
        assert b.importer.get("operator", "car5-state") is None
        assert b.federation_agent._tentative == {}


async def never_answers(*args: Any) -> Any:
    """A request handler that never answers."""
    await asyncio.Event().wait()


async def test_a_create_stream_that_fails_leaves_nothing_agreed(
    demo_keys: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # regression: B agreed before asking and kept it whatever the answer, so each mistyped
    # object stayed agreed for ever and "uav-a is gone; its streams imported here ended"
    # named streams that never existed
    async with memory_federation(demo_keys) as (ps, _):
        a, b, op = ps["uav-a"], ps["uav-b"], ps["operator"]
        fed = b.federation_agent
        car5 = a.instance.add_source("cars/car5/state")

        def agreed() -> list[str]:
            return sorted(r.semantic_label for r in b.importer.imports("uav-a"))

        with pytest.raises(Refused, match="car22-state"):  # uav-a has no car22
            await fed.create_stream("uav-a", ["car22-state"], timeout=WAIT)
        assert agreed() == []
        with pytest.raises(Refused, match="car22-state"):  # refused as a whole
            await fed.create_stream("uav-a", ["car5-state", "car22-state"], timeout=WAIT)
        assert agreed() == []
        with pytest.raises(UnknownSemanticLabel):  # refused here, before asking
            await fed.create_stream("uav-a", ["car5-state", "wind"], timeout=WAIT)
        assert agreed() == []

        # unreachable (not in the trust file), or silent (timed out): nothing either
        with pytest.raises(UnknownPlatform):
            await fed.create_stream("uav-z", ["car5-state"], timeout=WAIT)
        assert b.importer.get("uav-z", "car5-state") is None
        monkeypatch.setattr(op.federation_agent, "_create_stream", never_answers)
        with pytest.raises(ReplyTimeout):
            await fed.create_stream("operator", ["car5-state"], timeout=0.2)
        assert b.importer.get("operator", "car5-state") is None

        # accepted: agreed for good; a later refusal naming it too leaves it agreed
        await fed.create_stream("uav-a", ["car5-state"], timeout=WAIT)
        with pytest.raises(Refused, match="cancel it first"):
            await fed.create_stream("uav-a", ["car5-state"], timeout=WAIT)
        assert agreed() == ["car5-state"] and fed._tentative == {}
        car5.push(car_state(0, 1, "uav-a"))
        label = await b.imported("uav-a", "car5-state", timeout=WAIT)
        assert b.instance.latest(label).samples[0].value == car_state(0, 1, "uav-a")

        # cancelled while asking: agreed meanwhile (a batch may overtake the answer), then not
        a.instance.add_source("cars/car7/state")
        asking = asyncio.create_task(fed.create_stream("uav-a", ["car7-state"], timeout=WAIT))
        async with asyncio.timeout(WAIT):
            while agreed() != ["car5-state", "car7-state"]:  # noqa: ASYNC110
                await asyncio.sleep(0)
        asking.cancel()
        with pytest.raises(asyncio.CancelledError):
            await asking
        assert agreed() == ["car5-state"] and fed._tentative == {}

        # the same stream asked twice at once: one accepted, one refused; it stays agreed
        a.instance.add_source("cars/car9/state")
        answers = await asyncio.gather(
            fed.create_stream("uav-a", ["car9-state"], timeout=WAIT),
            fed.create_stream("uav-a", ["car9-state"], timeout=WAIT),
            return_exceptions=True,
        )
        assert sorted(type(x).__name__ for x in answers) == ["Refused", "str"]
        assert agreed() == ["car5-state", "car9-state"] and fed._tentative == {}


async def test_consented_streams_that_never_start_are_bounded_and_expire(
    demo_keys: Path,
) -> None:
    # regression: the operator asked uav-a for streams to uav-b that uav-a maps but has no
    # stream for; uav-b consented, uav-a refused, and the agreements stayed for good until
    # they filled max_waiting_imports and uav-b's own create-stream from uav-a was refused
    consent = {"sharing": {"accept_for": ["operator"]}}
    async with memory_federation(demo_keys, **consent) as (ps, _):
        a, b, op = ps["uav-a"], ps["uav-b"], ps["operator"]
        b.max_waiting_imports = 2
        b.consent_lease = 2.0  # long enough for the checks before it ends
        car5 = a.instance.add_source("cars/car5/state")
        car7 = a.instance.add_source("cars/car7/state")

        def agreed() -> list[str]:
            return sorted(r.semantic_label for r in b.importer.imports("uav-a"))

        with pytest.raises(Refused, match="no stream for it here"):  # uav-b consented
            await op.federation_agent.create_stream(
                "uav-a", ["car11-state", "car13-state"], to_units=["uav-b"], timeout=WAIT
            )
        assert agreed() == ["car11-state", "car13-state"]
        # more are refused by uav-b, which keeps none of their labels
        with pytest.raises(Refused, match=r"sent nothing yet \(at most 2\)"):
            await op.federation_agent.create_stream(
                "uav-a", ["car15-state", "car17-state"], to_units=["uav-b"], timeout=WAIT
            )
        assert agreed() == ["car11-state", "car13-state"]

        # uav-b's own requests are not denied by what others made it agree
        await b.federation_agent.create_stream("uav-a", ["car5-state"], timeout=WAIT)
        b.expect("uav-a", "car19-state")
        car5.push(car_state(0, 1, "uav-a"))
        await b.imported("uav-a", "car5-state", timeout=WAIT)
        # asking for a consented one ourselves: accepted, it is ours for good; refused, it
        # stays as it was (its lease goes on)
        a.instance.add_source("cars/car13/state")
        await b.federation_agent.create_stream("uav-a", ["car13-state"], timeout=WAIT)
        assert list(b._leased["uav-a"]) == ["car11-state"]
        with pytest.raises(Refused, match="no stream for it here"):
            await b.federation_agent.create_stream("uav-a", ["car11-state"], timeout=WAIT)
        assert "car11-state" in agreed()

        # the consents nobody acted on end with their lease, freeing their places
        async with asyncio.timeout(WAIT):
            while "car11-state" in agreed():  # noqa: ASYNC110
                await asyncio.sleep(0.05)
        assert agreed() == ["car13-state", "car19-state", "car5-state"]
        # a consented stream that starts stays after its lease
        await op.federation_agent.create_stream(
            "uav-a", ["car7-state"], to_units=["uav-b"], timeout=WAIT
        )
        car7.push(car_state(0, 1, "uav-a"))
        label = await b.imported("uav-a", "car7-state", timeout=WAIT)
        await asyncio.sleep(b.consent_lease + 0.2)
        assert agreed() == ["car13-state", "car19-state", "car5-state", "car7-state"]
        assert b.instance.latest(label).samples[0].value == car_state(0, 1, "uav-a")
        assert b._leased == {}


async def test_the_application_agreeing_while_our_request_waits_keeps_it(
    demo_keys: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # regression: `expect` found the pair agreed (tentatively, by our create-stream still
    # waiting) and left it tentative, so the request's failure withdrew the application's
    # agreement too
    async with memory_federation(demo_keys) as (ps, _):
        b, op = ps["uav-b"], ps["operator"]
        monkeypatch.setattr(op.federation_agent, "_create_stream", never_answers)
        asking = asyncio.create_task(
            b.federation_agent.create_stream("operator", ["car5-state"], timeout=0.5)
        )
        async with asyncio.timeout(WAIT):
            while not b.agreed("operator", "car5-state"):  # noqa: ASYNC110
                await asyncio.sleep(0)
        b.expect("operator", "car5-state")
        with pytest.raises(ReplyTimeout):
            await asking
        assert b.agreed("operator", "car5-state")
        assert b.federation_agent._tentative == {}


async def test_the_consent_bound_is_per_requester_too(demo_keys: Path) -> None:
    # regression: the bound on consented streams waiting for their first batch was one per
    # sender, so the operator's requests used up what uav-a itself could ask to send to uav-b
    consent = {"sharing": {"accept_for": ["operator", "uav-a"]}}
    async with memory_federation(demo_keys, **consent) as (ps, _):
        a, b, op = ps["uav-a"], ps["uav-b"], ps["operator"]
        b.max_waiting_imports, b.max_waiting_imports_per_requester = 3, 2

        def agreed() -> list[str]:
            return sorted(r.semantic_label for r in b.importer.imports("uav-a"))

        with pytest.raises(Refused, match="no stream for it here"):  # uav-b consented
            await op.federation_agent.create_stream(
                "uav-a", ["car11-state", "car13-state"], to_units=["uav-b"], timeout=WAIT
            )
        with pytest.raises(Refused, match=r"that operator asked for here .*at most 2 per"):
            await op.federation_agent.create_stream(
                "uav-a", ["car15-state"], to_units=["uav-b"], timeout=WAIT
            )
        assert agreed() == ["car11-state", "car13-state"]
        # another requester still has its share, up to the total per sender
        with pytest.raises(Refused, match="no stream for it here"):
            await a.federation_agent.create_stream(
                "uav-a", ["car17-state"], to_units=["uav-b"], timeout=WAIT
            )
        assert agreed() == ["car11-state", "car13-state", "car17-state"]
        with pytest.raises(Refused, match=r"have sent nothing yet \(at most 3\)"):
            await a.federation_agent.create_stream(
                "uav-a", ["car19-state"], to_units=["uav-b"], timeout=WAIT
            )
        assert agreed() == ["car11-state", "car13-state", "car17-state"]


async def test_a_provider_holds_a_bounded_number_of_streams_by_consent(demo_keys: Path) -> None:
    # attack: uav-a, in uav-b's accept_for, asked itself to stream its labels to uav-b and
    # sent a batch on each; started, they no longer counted as waiting, so the imports it
    # made at uav-b had no bound. Now it holds consented_import_limit of them, then refused
    consent = {"sharing": {"accept_for": ["uav-a"]}, "consented_import_limit": 3}
    async with memory_federation(demo_keys, **consent) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        assert b.max_consented_imports == 3
        b.max_waiting_imports = 1  # what no longer waits is not held by this bound
        cars = [a.instance.add_source(f"cars/car{k}/state") for k in range(5)]
        for k in range(3):
            await a.federation_agent.create_stream(
                "uav-a", [f"car{k}-state"], to_units=["uav-b"], timeout=WAIT
            )
            cars[k].push(car_state(k, 1, "uav-a"))
            await b.imported("uav-a", f"car{k}-state", timeout=WAIT)
        with pytest.raises(Refused, match=r"uav-a holds 3 streams here agreed by consent"):
            await a.federation_agent.create_stream(
                "uav-a", ["car3-state"], to_units=["uav-b"], timeout=WAIT
            )
        assert not b.agreed("uav-a", "car3-state")
        assert b.federation_agent.refusals.get("consent-limit") == 1
        recs = [r for r in b.interface.audit.records if r.get("code") == "consent-limit"]
        assert len(recs) == 1 and recs[0]["from"] == "uav-a", recs
        # uav-b's own requests are not counted, nor refused by it
        await b.federation_agent.create_stream("uav-a", ["car4-state"], timeout=WAIT)
        cars[4].push(car_state(4, 1, "uav-a"))
        await b.imported("uav-a", "car4-state", timeout=WAIT)
        # one that ended counts no more (a long-running receiver is not refused for ever);
        # it is withdrawn, so a batch of it cannot start it again uncounted
        ended = b.importer.get("uav-a", "car0-state")
        assert ended is not None and ended.local_label is not None
        b.importer._end(ended)  # as the sender's end does
        await a.federation_agent.create_stream(
            "uav-a", ["car3-state"], to_units=["uav-b"], timeout=WAIT
        )
        assert b.agreed("uav-a", "car3-state") and not b.agreed("uav-a", "car0-state")
        assert b.instance.latest(ended.local_label).samples[0].value == car_state(0, 1, "uav-a")


async def test_a_consent_while_our_request_waits_stays_under_its_lease(
    demo_keys: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # regression: uav-b's own create-stream for a label waited when the operator had uav-a
    # ask uav-b to receive it too; the consent took the label for good, so when uav-a then
    # refused both, it stayed agreed for ever instead of ending with the consent's lease
    consent = {"sharing": {"accept_for": ["operator"]}}
    async with memory_federation(demo_keys, **consent) as (ps, _):
        a, b, op = ps["uav-a"], ps["uav-b"], ps["operator"]
        b.consent_lease = 1.0
        a.instance.add_source("cars/car5/state")
        fed, create = a.federation_agent, a.federation_agent._create_stream
        answer = asyncio.Event()

        async def b_waits(req: Any, message: ACLMessage) -> Any:
            if message.sender.endswith("@uav-b"):
                await answer.wait()  # uav-b's request is answered when the test says
            return await create(req, message)

        monkeypatch.setattr(fed, "_create_stream", b_waits)

        async def consent_while_b_waits(labels: list[str]) -> Any:
            asking = asyncio.create_task(
                b.federation_agent.create_stream("uav-a", labels[:1], timeout=WAIT)
            )
            async with asyncio.timeout(WAIT):
                while not b.agreed("uav-a", labels[0]):  # noqa: ASYNC110
                    await asyncio.sleep(0)
            with pytest.raises(Refused, match="no stream for it here"):
                await op.federation_agent.create_stream(
                    "uav-a", labels, to_units=["uav-b"], timeout=WAIT
                )
            answer.set()
            try:
                return await asking
            finally:
                answer.clear()

        # ours refused too: the consent's lease decides, and ends it
        with pytest.raises(Refused, match="no stream for it here"):
            await consent_while_b_waits(["car11-state"])
        assert "car11-state" in b._leased["uav-a"]
        async with asyncio.timeout(WAIT):
            while b.agreed("uav-a", "car11-state"):  # noqa: ASYNC110
                await asyncio.sleep(0.02)
        # ours accepted: agreed for good, its lease ended (car13's, refused, goes on)
        await consent_while_b_waits(["car5-state", "car13-state"])
        assert list(b._leased["uav-a"]) == ["car13-state"]
        assert b.agreed("uav-a", "car5-state")


async def test_a_create_stream_we_gave_up_on_is_stopped_at_the_provider(
    demo_keys: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # regression: uav-b's create-stream timed out and uav-b withdrew its agreement, but
    # uav-a was not told: its export ran on until its lease (10 s), sending what nobody
    # agreed to; now uav-b cancels (FIPA cancel in the conversation) when it gives up
    async with memory_federation(demo_keys) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        a.instance.add_source("cars/car5/state")
        a.instance.add_source("cars/car7/state")
        fed = a.federation_agent
        create, start = fed._create_stream, fed._start_export
        go, started = asyncio.Event(), asyncio.Event()

        async def starts_late(*args: Any) -> Any:  # car5: still starting when cancelled
            await go.wait()
            try:
                return await start(*args)
            finally:
                started.set()

        async def answers_late(req: Any, message: ACLMessage) -> Any:  # car7: running
            result = await create(req, message)
            started.set()
            await go.wait()
            return result

        async def stopped_promptly() -> None:
            async with asyncio.timeout(WAIT):
                await started.wait()
            async with asyncio.timeout(a.config.export_lease / 2):  # not by its lease
                while fed.export_count or a.exporter.exports():  # noqa: ASYNC110
                    await asyncio.sleep(0.01)

        monkeypatch.setattr(fed, "_start_export", starts_late)
        with pytest.raises(ReplyTimeout):
            await b.federation_agent.create_stream("uav-a", ["car5-state"], timeout=0.3)
        received = fed.stats.received
        async with asyncio.timeout(WAIT):  # the cancel is there before the export starts
            while fed.stats.received == received:  # noqa: ASYNC110
                await asyncio.sleep(0.01)
        go.set()
        await stopped_promptly()

        monkeypatch.setattr(fed, "_start_export", start)
        monkeypatch.setattr(fed, "_create_stream", answers_late)
        go.clear()
        started.clear()
        with pytest.raises(ReplyTimeout):
            await b.federation_agent.create_stream("uav-a", ["car7-state"], timeout=0.5)
        await stopped_promptly()
        go.set()
        assert not b.agreed("uav-a", "car5-state") and not b.agreed("uav-a", "car7-state")

        # a global create-stream: those silent until the deadline are told too
        go.clear()
        started.clear()
        a.instance.add_source("cars/car9/state")
        asked = {"action": "create-stream", "labels": ["car9-state"]}
        result = await b.federation_agent.global_request(asked, deadline=0.5)
        assert result.no_answer == ["uav-a"]
        await stopped_promptly()
        go.set()


async def test_a_stream_that_flowed_before_we_gave_up_ends_here(
    demo_keys: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # regression: uav-b's create-stream timed out after samples had landed: the import
    # stayed agreed and live while the cancel stopped the export (no end marker follows a
    # cancel), so it never ended, and the local channel followed it as the node's own,
    # waiting for samples for ever
    from federation._local import LocalChannel

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(demo_keys / "run"))
    async with memory_federation(demo_keys) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        car5 = a.instance.add_source("cars/car5/state")
        fed = a.federation_agent
        create = fed._create_stream
        go = asyncio.Event()

        async def flows_then_answers_late(req: Any, message: ACLMessage) -> Any:
            result = await create(req, message)
            car5.push(car_state(0, 1, "uav-a"))
            await go.wait()
            return result

        monkeypatch.setattr(fed, "_create_stream", flows_then_answers_late)
        asking = asyncio.create_task(
            b.federation_agent.create_stream("uav-a", ["car5-state"], timeout=WAIT)
        )
        label = await b.imported("uav-a", "car5-state", timeout=WAIT)
        asking.cancel()  # given up, as a timeout does
        with pytest.raises(asyncio.CancelledError):
            await asking
        rec = b.importer.get("uav-a", "car5-state")
        assert rec is None and not b.agreed("uav-a", "car5-state")
        # what landed stays readable under its label
        assert b.instance.latest(label).samples[0].value == car_state(0, 1, "uav-a")
        async with asyncio.timeout(a.config.export_lease / 2):  # the cancel stopped it
            while fed.export_count or a.exporter.exports():  # noqa: ASYNC110
                await asyncio.sleep(0.01)
        go.set()

        monkeypatch.setattr(fed, "_create_stream", create)
        channel = LocalChannel(b)
        entry = await channel._acquire("uav-a", "car5-state", None, WAIT)
        assert entry is not None  # asked anew, not followed as the node's own
        car5.push(car_state(1, 2, "uav-a"))
        async with asyncio.timeout(WAIT):
            while b.instance.latest(label).samples[0].value != car_state(1, 2, "uav-a"):  # noqa: ASYNC110
                await asyncio.sleep(0.01)
        await channel._release("uav-a", entry)


async def test_a_sender_gone_names_apart_the_streams_that_never_flowed(
    demo_keys: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # regression: "uav-b is gone; its streams imported here ended" also named agreed
    # streams whose first sample never came
    async with memory_federation(demo_keys) as (ps, b_stack):
        a, b = ps["uav-a"], ps["uav-b"]
        car5 = b.instance.add_source("tracks/car5/state")
        await a.federation_agent.create_stream("uav-b", ["car5-state"], timeout=WAIT)
        car5.push(car_state(0, 1, "uav-b"))
        await a.imported("uav-b", "car5-state", timeout=WAIT)
        a.expect("uav-b", "car7-state")  # agreed, never sent
        caplog.set_level(logging.WARNING, logger="federation._platform")
        async with a.membership() as events:
            await b_stack.aclose()
            async with asyncio.timeout(WAIT):
                await next_event(events, MembershipEvent("gone", "uav-b"))
        async with asyncio.timeout(WAIT):
            while not any("is gone" in r.getMessage() for r in caplog.records):  # noqa: ASYNC110
                await asyncio.sleep(0.01)
        gone = [r.getMessage() for r in caplog.records if "is gone" in r.getMessage()]
        assert gone == [
            "platform uav-a: uav-b is gone; its streams imported here ended: car5-state",
            "platform uav-a: uav-b is gone; its streams agreed here that were waiting for "
            "their first sample will not come: car7-state",
        ]


async def test_the_local_channel_releases_only_what_a_command_took(
    demo_keys: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # regression: a command that followed the node's own import released it anyway,
    # cancelling the export another command had made since; and a cancel to a silent target
    # held the channel's lock (2 s), so every other command queued behind it
    from federation._local import LocalChannel

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(demo_keys / "run"))
    async with memory_federation(demo_keys) as (ps, _):
        a, b, op = ps["uav-a"], ps["uav-b"], ps["operator"]
        car5 = a.instance.add_source("cars/car5/state")
        op.instance.add_source("picture/car7")
        channel = LocalChannel(b)
        own = await b.federation_agent.create_stream("uav-a", ["car5-state"], timeout=WAIT)
        car5.push(car_state(0, 1, "uav-a"))
        await b.imported("uav-a", "car5-state", timeout=WAIT)
        follower = await channel._acquire("uav-a", "car5-state", None, WAIT)
        assert follower is None  # the node's own: followed, not counted
        await b.federation_agent.cancel_stream("uav-a", own, timeout=WAIT)
        b.importer.forget("uav-a", "car5-state")  # the node's own import ends
        maker = await channel._acquire("uav-a", "car5-state", None, WAIT)
        # the follower, leaving, has nothing to give back: only the maker counts
        assert maker is not None and maker.following == 1
        assert a.federation_agent.export_count == 1

        # the last one out cancels; a silent target does not hold up another stream
        monkeypatch.setattr(a.federation_agent, "_cancel_stream", never_answers)
        releasing = asyncio.create_task(channel._release("uav-a", maker))
        async with asyncio.timeout(WAIT):
            while ("uav-a", "car5-state") not in channel._pending:  # noqa: ASYNC110
                await asyncio.sleep(0)
        other = await channel._acquire("operator", "car7-state", None, WAIT)
        assert other is not None and not releasing.done()
        async with asyncio.timeout(WAIT):
            await releasing
        await channel._release("operator", other)
        assert op.federation_agent.export_count == 0


async def test_a_cancelled_command_gives_back_every_stream_it_took(
    demo_keys: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # regression: a command cancelled (the node stopping) while it released the first of
    # its streams never released the others: counted for ever, their exports never
    # cancelled; and a sample period that is no number failed formatting the refusal
    from federation._cli_common import NotAnsweredError
    from federation._local import LocalChannel

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(demo_keys / "run"))
    async with memory_federation(demo_keys) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        a.instance.add_source("cars/car5/state")
        a.instance.add_source("cars/car7/state")
        channel = LocalChannel(b)
        relaying = asyncio.Event()

        async def relays_for_ever(*args: Any) -> None:
            relaying.set()
            await asyncio.Event().wait()

        monkeypatch.setattr(channel, "_relay", relays_for_ever)
        request: dict[str, Any] = {
            "op": "stream",
            "platform": "uav-a",
            "labels": ["car5-state", "car7-state"],
        }
        command = asyncio.create_task(channel._stream(request, None, None, WAIT, WAIT))  # type: ignore[arg-type]
        async with asyncio.timeout(WAIT):
            await relaying.wait()
        assert len(channel._exports) == 2 and a.federation_agent.export_count == 2
        for bad in ("1", True, -1, 0, float("nan"), float("inf"), [1]):
            asking = dict(request, sample_period=bad)
            with pytest.raises(NotAnsweredError, match="bad request: sample_period must be"):
                await channel._stream(asking, None, None, WAIT, WAIT)  # type: ignore[arg-type]
        monkeypatch.setattr(a.federation_agent, "_cancel_stream", never_answers)
        command.cancel()
        async with asyncio.timeout(WAIT):
            while ("uav-a", "car5-state") not in channel._pending:  # noqa: ASYNC110
                await asyncio.sleep(0)
        command.cancel()  # again, while the first release waits for its cancel's answer
        with pytest.raises(asyncio.CancelledError):
            await command
        async with asyncio.timeout(WAIT):
            while channel._exports or channel._pending:  # noqa: ASYNC110
                await asyncio.sleep(0.01)


async def test_a_stream_that_flows_before_the_refusal_ends_here(
    demo_keys: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the race: the provider's batches overtake its answer, then the answer is a failure
    # and the provider stops what it started (no end marker). It stayed agreed and never
    # ended: followers waited for ever and a later request for it was never made. Now it
    # ends here; the samples that landed stay readable under its label
    async with memory_federation(demo_keys) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        car5 = a.instance.add_source("cars/car5/state")
        fed = a.federation_agent
        create = fed._create_stream
        followers: list[Any] = []

        async def streams_then_fails(req: Any, message: ACLMessage) -> Any:
            export = a.exporter.start_exporting("cars/car5/state", "car5-state", "uav-b")
            car5.push(car_state(0, 1, "uav-a"))
            label = await b.imported("uav-a", "car5-state", timeout=WAIT)
            followers.append(b.instance.subscribe(label, Policy(start=0)))
            await a.exporter.stop(export)  # what was started stops (no end marker)
            raise Failure("the exporter failed")

        monkeypatch.setattr(fed, "_create_stream", streams_then_fails)
        with pytest.raises(Failed, match="the exporter failed"):
            await b.federation_agent.create_stream(
                "uav-a", ["car5-state", "car7-state"], timeout=WAIT
            )
        assert b.importer.imports("uav-a") == [] and not b.agreed("uav-a", "car5-state")
        async with asyncio.timeout(WAIT):  # the follower's iterator ends
            got = [s.value async for s in followers[0]]
        assert got == [car_state(0, 1, "uav-a")]
        label = b.import_label("uav-a", "car5-state")
        assert b.instance.latest(label).samples[0].value == car_state(0, 1, "uav-a")
        # asked again, it flows again into the same label
        monkeypatch.setattr(fed, "_create_stream", create)
        await b.federation_agent.create_stream("uav-a", ["car5-state"], timeout=WAIT)
        car5.push(car_state(1, 2, "uav-a"))
        async with asyncio.timeout(WAIT):
            while b.instance.latest(label).samples[0].value != car_state(1, 2, "uav-a"):  # noqa: ASYNC110
                await asyncio.sleep(0.01)


async def test_samples_dropped_before_sending_are_not_counted_again_as_lost_in_transit() -> None:
    # regression: numbered, then dropped for want of a session, a batch showed up twice:
    # as no-session at the provider and again when the receiver reported the gap
    from agents._exceptions import UnknownSession
    from federation._export import ExportProxy
    from federation._import import ImportProxy
    from federation._sessions import PlainSessions

    class Flaky(PlainSessions):
        fail = 0

        def seal_bytes(self, peer: str, body: bytes) -> bytes:
            if self.fail:
                self.fail -= 1
                raise UnknownSession("no session yet", peer)
            return super().seal_bytes(peer, body)

        async def ensure(self, peer: str) -> None:
            raise UnknownSession("cannot agree now", peer)

    hub = MemoryHub()
    async with (
        hub.transport() as ta,
        hub.transport() as tb,
        DyKnowInstance("a") as ia,
        DyKnowInstance("b") as ib,
    ):
        src = ia.add_source("x")
        sessions = Flaky("a")
        exporter = ExportProxy("a", "demo", ta, ia, sessions, agree_timeout=0.1)
        importer = ImportProxy(
            "b", "demo", tb, ib, PlainSessions("b"), lambda s, lab: "in/x", report_interval=0.05
        )
        async with exporter, importer:
            export = exporter.start_exporting("x", "x", "b")
            async with asyncio.timeout(WAIT):
                src.push(1.0)
                while export.sent < 1:  # noqa: ASYNC110
                    await asyncio.sleep(0.01)
                sessions.fail = 1
                src.push(2.0)
                while not export.dropped.get("no-session"):  # noqa: ASYNC110
                    await asyncio.sleep(0.01)
                src.push(3.0)
                while (rec := importer.get("a", "x")) is None or rec.injected < 2:  # noqa: ASYNC110
                    await asyncio.sleep(0.01)
                assert rec.lost == 1  # the receiver sees the gap …
                while export._claimed < 1:  # noqa: ASYNC110
                    await asyncio.sleep(0.01)  # … and its report of it is taken …
        assert export.dropped == {"no-session": 1}  # … but it is not counted twice


async def test_the_commands_waiting_on_a_failed_create_stream_fail_with_it(
    demo_keys: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # regression: the commands waiting on the channel's create-stream to a dead target
    # each asked again after it failed, one after another: the k-th waited k timeouts
    from federation._local import LocalChannel

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(demo_keys / "run"))
    async with memory_federation(demo_keys) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        monkeypatch.setattr(a.federation_agent, "_create_stream", never_answers)
        channel = LocalChannel(b)
        start = time.monotonic()
        # one after another they took 3 timeouts, together 1: 2 parts them with a second's
        # margin either side, for a busy machine's stalls
        commands = [channel._acquire("uav-a", "car5-state", None, 1.0) for _ in range(3)]
        results = await asyncio.gather(*commands, return_exceptions=True)
        assert all(isinstance(r, ReplyTimeout) for r in results), results
        assert time.monotonic() - start < 2.0  # one timeout for all three
        assert channel._pending == {}


async def test_a_receiver_in_members_before_its_snapshot_answered_is_waited_for(
    demo_keys: Path,
) -> None:
    """A member that just joined is in `members` (its signed events) before its directory
    snapshot answered at the provider: a stream asked to it then is not refused in that
    gap; the provider waits (one query timeout at most) for it to be listed."""
    consent = {"sharing": {"accept_for": ["uav-b"]}}
    async with memory_federation(demo_keys, **consent) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        gdf = a.agents.global_df
        assert gdf is not None
        gdf.query_timeout = WAIT  # the wait's bound: far beyond what the test takes
        a.instance.add_source("cars/car5/state")
        # the operator's snapshot, at uav-a, asked now (as right after it joined): in
        # `platforms` (and `members`), not listed
        gdf._joining.add("operator")
        assert "operator" in gdf.platforms and "operator" not in gdf.listed
        fed_a = a.federation_agent
        waiting = asyncio.Event()
        original = fed_a._await_listed

        async def noted(receivers: list[str], requester: str) -> None:
            waiting.set()
            await original(receivers, requester)

        fed_a._await_listed = noted  # type: ignore[method-assign]
        asking = asyncio.ensure_future(
            b.federation_agent.create_stream(
                "uav-a", ["car5-state"], to_units=["operator"], timeout=WAIT
            )
        )
        async with asyncio.timeout(WAIT):
            await waiting.wait()
        gdf._joining.discard("operator")  # its snapshot answered: listed
        async with asyncio.timeout(WAIT):
            export_id = await asking
        assert a.federation_agent.exports[export_id].receivers == ["operator"]
        assert a.federation_agent.refusals.get("unlisted-receiver") is None


async def test_a_refusal_quoting_what_a_member_asked_is_logged_as_one_capped_line(
    demo_keys: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A member asks uav-a to confirm a stream of 64 labels of 200 characters each, which
    uav-a never asked for: refused, counted and audited (the reason whole), and logged on
    one line whose quote of the labels is cut to `QUOTE_MAX` characters, not 13 kB."""
    from federation._quote import QUOTE_MAX

    async with memory_federation(demo_keys) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        mallory = await b.agents.add(Agent("mallory"))
        labels = [f"car{i}-state\nINFO federation: {'x' * 200}"[:200] for i in range(64)]
        content = {"action": "confirm-stream", "provider": "operator", "labels": labels}
        with (
            caplog.at_level("INFO", logger="federation._service"),
            pytest.raises(Refused) as refused,
        ):
            await request(mallory, "federation@uav-a", content, ontology=ONTOLOGY, timeout=WAIT)
        assert refused.value.message is not None
        told = str(refused.value.message.content)
        assert told.startswith("uav-a asked operator for no stream of ['car0-state\\nINFO")
        assert a.federation_agent.refusals.get("consent") == 1
        [record] = [r for r in a.interface.audit.records if r.get("code") == "consent"]
        assert record["sender"] == "mallory@uav-b" and len(record["reason"]) > 13_000
        said = [r.getMessage() for r in caplog.records if "refused mallory@uav-b" in r.getMessage()]
        assert len(said) == 1 and "\n" not in said[0]
        reason = said[0].split("refused mallory@uav-b: ", 1)[1]
        assert (
            reason
            == f"{told[:QUOTE_MAX]}… ({len(told)} characters, {len(told) - QUOTE_MAX} left out)"
        )


async def test_a_members_refusal_of_a_followed_stream_is_logged_as_one_capped_line(
    demo_keys: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """uav-a, turned hostile, refuses the stream uav-b's console follows with 10 kB that
    forge a log line and clear the operator's terminal: the follower logs it on one line,
    the newline and the escape escaped, cut to `QUOTE_MAX` characters with how long it was;
    the stream is refused, its reason kept for the page as bounded as the log line."""
    from agents import Refuse
    from federation import _follow
    from federation._follow import FollowedStream
    from federation._quote import QUOTE_MAX, quoted

    forged = "stopped\nCRITICAL federation: all keys leaked \x1b[2J"
    why = forged + "x" * 10_000

    async def hostile(*args: Any, **kwargs: Any) -> Any:
        raise Refuse(why)

    async with memory_federation(demo_keys) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        a.federation_agent._perform = hostile  # type: ignore[method-assign]
        stream = FollowedStream("car5-state")
        refused = asyncio.Event()
        with caplog.at_level("INFO", logger="federation.follow"):
            asking = asyncio.create_task(
                _follow._ask_for(b, "uav-a", stream, lambda: True, refused.set)
            )
            try:
                await asyncio.wait_for(refused.wait(), WAIT)
            finally:
                asking.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await asking
        assert stream.state == "refused" and stream.error == quoted(f"refused: {why}")
        assert "\n" not in stream.error and "\x1b" not in stream.error
        said = [
            r.getMessage() for r in caplog.records if " refused car5-state to " in r.getMessage()
        ]
        assert len(said) == 1 and "\n" not in said[0] and "\x1b" not in said[0]
        told = f"federation@uav-a refused: {why}"
        kept = QUOTE_MAX - 2 * 3  # two characters escaped, four characters each
        shown = told[:kept].replace("\n", "\\x0a").replace("\x1b", "\\x1b")
        assert said[0] == (
            f"uav-a refused car5-state to uav-b: {shown}… ({len(told)} characters, "
            f"{len(told) - kept} left out) (asked again every {_follow.RETRY:g} s)"
        )


async def test_a_members_refusal_to_cancel_a_followed_stream_is_logged_as_one_capped_line(
    demo_keys: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """uav-a, turned hostile, refuses to cancel the export of a stream uav-b's console
    stops following with 10 kB that forge a log line and clear the terminal: the follower
    logs it on one line, escaped and cut to `QUOTE_MAX` characters with how long it was."""
    from agents import Refuse
    from federation import _follow
    from federation._follow import FollowedStream
    from federation._quote import QUOTE_MAX

    forged = "gone\nCRITICAL federation: all keys leaked \x1b[2J"
    why = forged + "x" * 10_000

    async def hostile(*args: Any, **kwargs: Any) -> Any:
        raise Refuse(why)

    async with memory_federation(demo_keys) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        a.federation_agent._perform = hostile  # type: ignore[method-assign]
        stream = FollowedStream("car5-state")
        stream.export_id = "x-1"
        with caplog.at_level("INFO", logger="federation.follow"):
            await asyncio.wait_for(_follow.cancel_export(b, "uav-a", stream), WAIT)
        said = [r.getMessage() for r in caplog.records if "cancelling x-1 at " in r.getMessage()]
        assert len(said) == 1 and "\n" not in said[0] and "\x1b" not in said[0]
        told = f"refused: {why}"
        kept = QUOTE_MAX - 2 * 3  # two characters escaped, four characters each
        shown = told[:kept].replace("\n", "\\x0a").replace("\x1b", "\\x1b")
        assert said[0] == (
            f"cancelling x-1 at uav-a: {shown}… ({len(told)} characters, "
            f"{len(told) - kept} left out)"
        )


async def test_a_members_refusal_to_cancel_a_commands_export_is_logged_as_one_capped_line(
    demo_keys: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """uav-a agrees to a one-shot command's stream, then refuses its cancel with 10 kB that
    forge a log line and clear the terminal: the command logs it on one line, escaped and
    cut to `QUOTE_MAX` characters with how long it was."""
    from agents import Refuse
    from federation import _cli_net
    from federation._quote import QUOTE_MAX
    from federation._service import CancelStream

    why = "gone\nCRITICAL federation: all keys leaked \x1b[2J" + "x" * 10_000

    async with memory_federation(demo_keys) as (ps, _):
        a, b = ps["uav-a"], ps["uav-b"]
        perform = a.federation_agent._perform

        async def hostile(req: Any, message: Any) -> Any:
            if isinstance(req, CancelStream):
                raise Refuse(why)
            return await perform(req, message)

        a.federation_agent._perform = hostile  # type: ignore[method-assign]
        a.instance.add_source("cars/car5/state")
        with caplog.at_level("INFO", logger="federation"):
            async with _cli_net._exported(
                b, "uav-a", ["car5-state"], sample_period=None, wait=WAIT, timeout=WAIT
            ):
                pass
        said = [
            r.getMessage() for r in caplog.records if "cancelling the export " in r.getMessage()
        ]
        assert len(said) == 1 and "\n" not in said[0] and "\x1b" not in said[0]
        told = f"federation@uav-a refused: {why}"
        kept = QUOTE_MAX - 2 * 3  # two characters escaped, four characters each
        shown = told[:kept].replace("\n", "\\x0a").replace("\x1b", "\\x1b")
        assert said[0].endswith(
            f" at uav-a: {shown}… ({len(told)} characters, {len(told) - kept} left out)"
        )
