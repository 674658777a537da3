"""The operator console's backend, over HTTP, against a small federation in one process.

The operator (with its `OperatorConsole`) and two fake UAVs share a `MemoryHub`; each UAV
publishes the demo's local labels (`federation.demo._vocabulary`) from a pusher task.
The tests read the model as the page does (Server-Sent Events from ``/api/events``) and
drive the query, search, policy and observation endpoints, good input and bad, holding
the console's token (`client`: ``Authorization: Bearer``). The attacks on who may use
the console are in tests/test_console_access.py (a spawned ``dyknow console``); here, the
one that needs a live export: a rebinding page must not re-create uav-a's.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from agents.keys import gen_keys, trust_keys
from agents.transports import MemoryHub
from dyknow_core import Source
from federation import FederationPlatform, PlatformConfig, PlatformConfigError
from federation.console import ConsoleSettings, OperatorConsole
from federation.demo._vocabulary import console_config, local_mapping, vocabulary

WAIT = 10.0  # the bound on any single wait
PUSH = 0.05  # s between two samples of a fake UAV (20 Hz)
UAVS = ["uav-a", "uav-b"]
STREAM_LABELS = console_config()["streams"]  # what the demo's operator config streams
WORLD = {
    "width": 1000,
    "height": 600,
    "roads": [{"id": "r1", "a": [0, 300], "b": [1000, 300], "speed_limit": 14, "lanes": 2}],
    "crossings": [{"id": "c1", "x": 500, "y": 300, "radius": 12, "roads": ["r1"]}],
    "areas": [{"index": 0, "polygon": [[0, 0], [500, 0], [500, 600], [0, 600]]}],
}


def config(tmp_path: Path, name: str) -> PlatformConfig:
    """A platform of the federation ``demo`` with the traffic demo's labels (and console)."""
    return PlatformConfig.from_dict(
        {
            "name": name,
            "federation": "demo",
            "key": str(tmp_path / "keys" / f"{name}.key"),
            "trust": str(tmp_path / "trust.json"),
            "vocabulary": vocabulary(),
            "mapping": local_mapping(),
            "console": console_config(),
        }
    )


@pytest.fixture
def demo_keys(tmp_path: Path) -> Path:
    pubs = [gen_keys(name, tmp_path / "keys")[2] for name in ["operator", *UAVS, "uav-c"]]
    trust_keys(tmp_path / "trust.json", pubs, federation="demo")
    return tmp_path


@dataclass
class FakeUav:
    """A UAV's demo streams, pushed at 20 Hz: it flies east, tracks two cars."""

    platform: FederationPlatform
    index: int
    sources: dict[str, Source] = field(default_factory=dict)
    violations: list[dict[str, Any]] = field(default_factory=list)
    k: int = 0

    def __post_init__(self) -> None:
        labels = self.platform.labels
        for semantic in STREAM_LABELS:
            local = labels.to_local(semantic)
            self.sources[semantic] = self.platform.instance.add_source(local)

    @property
    def name(self) -> str:
        return self.platform.name

    def push(self) -> None:
        self.k += 1
        x0 = 500.0 * self.index
        s = self.sources
        s["heli-position"].push({"x": x0 + 250 + self.k % 50, "y": 300.0, "z": 60.0})
        s["area"].push(
            {
                "index": self.index,
                "polygon": [[x0, 0], [x0 + 500, 0], [x0 + 500, 600], [x0, 600]],
                "delegated-by": None,
            }
        )
        cars = [
            {"id": f"{self.name}/car{i}", "x": x0 + 10 * i + self.k % 400, "y": 300.0,
             "speed": 12.5, "colour": "red", "road": "r1"}
            for i in (1, 2)
        ]  # fmt: skip
        s["tracked-cars"].push({"cars": cars})
        for v in self.violations:
            s["violation"].push(v)
        self.violations.clear()

    async def run(self) -> None:
        while True:
            self.push()
            await asyncio.sleep(PUSH)


@dataclass
class Federation:
    """The operator with its console, the fake UAVs, a way to start and to stop one."""

    hub: MemoryHub
    keys: Path
    operator: FederationPlatform
    uavs: dict[str, FakeUav] = field(default_factory=dict)
    stacks: dict[str, contextlib.AsyncExitStack] = field(default_factory=dict)
    console: OperatorConsole | None = None

    @property
    def url(self) -> str:
        assert self.console is not None
        return self.console.url

    async def start(self, name: str, index: int, *, streams: bool = True) -> FederationPlatform:
        """A UAV joins (``streams=False``: one without the demo's streams, for now)."""
        async with contextlib.AsyncExitStack() as own:
            t = await own.enter_async_context(self.hub.transport())
            p = await own.enter_async_context(
                FederationPlatform(config(self.keys, name), transport=t, join=False)
            )
            if streams:
                uav = self.uavs[name] = FakeUav(p, index)
                pusher = asyncio.create_task(uav.run(), name=f"test.push[{name}]")
                own.push_async_callback(_cancelled, pusher)
            await p.join()
            self.stacks[name] = own.pop_all()
        return p

    async def stop(self, name: str) -> None:
        """The UAV goes (its transport closes: its liveliness token goes)."""
        await self.stacks.pop(name).aclose()

    async def aclose(self) -> None:
        for name in list(self.stacks):
            await self.stop(name)


@contextlib.asynccontextmanager
async def console_federation(tmp_path: Path, **options: Any) -> AsyncIterator[Federation]:
    """Operator + console + fake UAVs on one MemoryHub, every UAV listed by the operator."""
    hub = MemoryHub()
    async with contextlib.AsyncExitStack() as stack:
        async with asyncio.timeout(WAIT):
            t = await stack.enter_async_context(hub.transport())
            operator = await stack.enter_async_context(
                FederationPlatform(config(tmp_path, "operator"), transport=t)
            )
            fed = Federation(hub, tmp_path, operator)
            stack.push_async_callback(fed.aclose)
            async with operator.membership() as events:
                for i, name in enumerate(UAVS):
                    await fed.start(name, i)
                while not set(UAVS) <= set(operator.members):
                    await events.get()
            fed.console = await stack.enter_async_context(
                OperatorConsole(operator, world_map=WORLD, **options)
            )
        yield fed


def client(fed: Federation, **options: Any) -> aiohttp.ClientSession:
    """An HTTP client of the console holding its token (as a script would: a Bearer)."""
    assert fed.console is not None
    return aiohttp.ClientSession(
        headers={"Authorization": f"Bearer {fed.console.token}"}, **options
    )


async def _cancelled(task: asyncio.Task[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


async def until_state(
    http: aiohttp.ClientSession,
    url: str,
    want: Callable[[dict[str, Any]], bool],
    timeout: float = WAIT,
) -> dict[str, Any]:
    """The first model pushed on ``/api/events`` that ``want`` accepts."""
    last: dict[str, Any] = {}
    try:
        async with asyncio.timeout(timeout), http.get(url + "api/events") as r:
            assert r.headers["Content-Type"].startswith("text/event-stream")
            async for line in r.content:
                if line.startswith(b"data: "):
                    last = json.loads(line[6:])
                    if want(last):
                        return last
    except TimeoutError:
        pass
    raise AssertionError(f"the console never showed it; last state: {json.dumps(last)[:2000]}")


def platform(state: dict[str, Any], name: str) -> dict[str, Any]:
    return next(p for p in state["platforms"] if p["name"] == name)


def stream(state: dict[str, Any], name: str, label: str) -> dict[str, Any]:
    return next(s for s in platform(state, name)["streams"] if s["label"] == label)


def filled(state: dict[str, Any], name: str) -> bool:
    """Every stream of ``name`` active, its position, area and cars known."""
    p = next((p for p in state["platforms"] if p["name"] == name), None)
    return (
        p is not None
        and p["state"] == "alive"
        and all(s["state"] == "active" for s in p["streams"])
        and p["position"] is not None
        and p["area"] is not None
        and len(p["cars"]) == 2
    )


async def post(http: aiohttp.ClientSession, url: str, body: Any) -> tuple[int, Any]:
    data = body if isinstance(body, str) else json.dumps(body)
    async with http.post(url, data=data, headers={"Content-Type": "application/json"}) as r:
        return r.status, await r.json()


# -- the model -------------------------------------------------------------------------------


async def test_state_fills_in_and_a_uav_that_goes_is_shown_gone(demo_keys: Path) -> None:
    async with console_federation(demo_keys) as fed, client(fed) as http:
        url = fed.url
        assert url.startswith("http://127.0.0.1:")
        async with http.get(url) as r:
            assert r.status == 200 and "<canvas" in await r.text()
        for name in ("app.js", "style.css"):
            async with http.get(url + f"static/{name}") as r:
                assert r.status == 200, name

        state = await until_state(http, url, lambda s: all(filled(s, n) for n in UAVS))
        assert state["operator"] == "operator" and state["world"] == WORLD
        assert [p["name"] for p in state["platforms"]] == UAVS  # not the operator itself
        a = platform(state, "uav-a")
        assert {c["id"] for c in a["cars"]} == {"uav-a/car1", "uav-a/car2"}
        assert a["area"]["polygon"][1] == [500.0, 0.0] and a["position"]["z"] == 60.0
        assert a["samples"] > 0 and a["last"] is not None
        assert [s["label"] for s in a["streams"]] == list(STREAM_LABELS)
        assert all(s["export_id"] and s["sample_period"] is None for s in a["streams"])
        # the config's streams and roles, for the page (drawn by role: no value of their own)
        assert state["streams"] == STREAM_LABELS and state["roles"]["tracks"] == "tracked-cars"
        assert state["observation_label"] == "observation"
        assert all(s["value"] is None for s in a["streams"])
        exports = fed.uavs["uav-a"].platform.federation_agent.exports
        assert {s["export_id"] for s in a["streams"]} == set(exports)

        # a violation is listed, newest first, with who reported it
        v = {"kind": "reckless-overtake", "car": "uav-a/car1", "other": "uav-a/car2",
             "start": 1.0, "end": 2.0, "x": 120.0, "y": 300.0, "platform": "uav-a",
             "fused": False}  # fmt: skip
        fed.uavs["uav-a"].violations.append(v)
        state = await until_state(http, url, lambda s: len(s["violations"]) == 1)
        assert state["violations"][0]["kind"] == "reckless-overtake"
        assert state["violations"][0]["reported-by"] == "uav-a"
        fed.uavs["uav-a"].violations.append({**v, "kind": "overtake"})
        state = await until_state(http, url, lambda s: len(s["violations"]) == 2)
        assert [x["kind"] for x in state["violations"]] == ["overtake", "reckless-overtake"]

        # uav-b goes: kept on the list as gone, its cars off the map; uav-a carries on
        await fed.stop("uav-b")
        state = await until_state(http, url, lambda s: platform(s, "uav-b")["state"] == "gone")
        b = platform(state, "uav-b")
        assert b["cars"] == [] and all(s["state"] == "ended" for s in b["streams"])
        assert platform(state, "uav-a")["state"] == "alive"
        async with http.get(url + "api/state") as r:
            assert r.status == 200 and platform(await r.json(), "uav-b")["state"] == "gone"


async def test_a_uav_that_comes_back_is_alive_and_streams_again(demo_keys: Path) -> None:
    async with console_federation(demo_keys) as fed, client(fed) as http:
        url = fed.url
        state = await until_state(http, url, lambda s: filled(s, "uav-b"))
        samples = platform(state, "uav-b")["samples"]
        await fed.stop("uav-b")
        await until_state(http, url, lambda s: platform(s, "uav-b")["state"] == "gone")
        await fed.start("uav-b", 1)  # the same name again: a restarted process
        state = await until_state(
            http, url, lambda s: filled(s, "uav-b") and platform(s, "uav-b")["samples"] > samples
        )
        exports = fed.uavs["uav-b"].platform.federation_agent.exports
        assert {s["export_id"] for s in platform(state, "uav-b")["streams"]} == set(exports)


# -- the requests ----------------------------------------------------------------------------


async def test_query_returns_samples_and_bad_queries_name_the_field(demo_keys: Path) -> None:
    async with console_federation(demo_keys) as fed, client(fed) as http:
        url = fed.url
        await until_state(http, url, lambda s: filled(s, "uav-a"))
        q = url + "api/query"
        status, latest = await post(http, q, {"platform": "uav-a", "label": "tracked-cars"})
        assert status == 200, latest
        assert latest["kind"] == "latest" and len(latest["samples"]) == 1
        sample = latest["samples"][0]
        assert {c["id"] for c in sample["value"]["cars"]} == {"uav-a/car1", "uav-a/car2"}
        assert math.isclose(sample["valid"], latest["query_time"], abs_tol=2.0)

        status, at = await post(
            http, q, {"platform": "uav-a", "label": "heli-position", "kind": "at", "at": -0.1}
        )
        assert status == 200 and len(at["samples"]) == 1
        assert at["samples"][0]["valid"] <= at["query_time"] - 0.1
        status, between = await post(
            http,
            q,
            {"platform": "uav-a", "label": "area", "kind": "between", "from": -1, "to": 0},
        )
        assert status == 200 and len(between["samples"]) >= 2  # 20 Hz for a second
        assert all(
            between["query_time"] - 1 <= s["valid"] <= between["query_time"]
            for s in between["samples"]
        )

        bad = {
            "platform": {"label": "area"},
            "label": {"platform": "uav-a", "label": "weather"},
            "kind": {"platform": "uav-a", "label": "area", "kind": "soon"},
            "at": {"platform": "uav-a", "label": "area", "kind": "at", "at": "yesterday"},
            "from": {"platform": "uav-a", "label": "area", "kind": "between", "from": True},
        }
        for key, body in bad.items():
            status, answer = await post(http, q, body)
            assert status == 400 and answer["error"].startswith(f"{key}: "), (key, answer)
        status, answer = await post(http, q, {"platform": "uav-z", "label": "area"})
        assert status == 400 and "uav-z" in answer["error"]
        for body in ("{not json", "[1, 2]"):
            status, answer = await post(http, q, body)
            assert status == 400 and answer["error"].startswith("body: "), answer

        # the platform refuses: it has no stream for that label
        status, answer = await post(http, q, {"platform": "uav-a", "label": "heli-altitude"})
        assert status == 502 and "heli-altitude" in answer["error"], answer


async def test_label_search_asks_every_platform(demo_keys: Path) -> None:
    async with console_federation(demo_keys) as fed, client(fed) as http:
        url = fed.url + "api/search"
        status, answer = await post(http, url, {"formula": "(all ?x (Car ?x))"})
        assert status == 200, answer
        assert sorted(answer["answers"]) == ["operator", *UAVS]
        assert answer["refused"] == {} and answer["no_answer"] == [] and answer["unlisted"] == []
        for body in ({"formula": "(all ?x (Car ?x)"}, {"formula": ""}, {"formula": 3}, {}):
            status, answer = await post(http, url, body)
            assert status == 400 and answer["error"].startswith("formula: "), (body, answer)
        # a concept the vocabulary does not have is named before anyone is asked
        status, answer = await post(http, url, {"formula": "(all ?x (Truck ?x))"})
        assert status == 400 and "Truck" in answer["error"], answer
        # whether anything matches is each platform's answer, the operator's too
        status, answer = await post(http, url, {"formula": "(iota ?x (Car ?x))"})
        assert status == 200 and "nothing satisfies" in answer["refused"]["operator"], answer


async def test_policy_change_recreates_the_export_and_the_rate_follows(demo_keys: Path) -> None:
    async with console_federation(demo_keys) as fed, client(fed) as http:
        url = fed.url
        state = await until_state(http, url, lambda s: filled(s, "uav-a"))
        old_id = stream(state, "uav-a", "tracked-cars")["export_id"]
        body = {"platform": "uav-a", "label": "tracked-cars", "sample_period": 0.5}
        status, answer = await post(http, url + "api/policy", body)
        assert status == 200, answer
        assert answer["stream"]["sample_period"] == 0.5
        new_id = answer["stream"]["export_id"]
        assert new_id != old_id
        exports = fed.uavs["uav-a"].platform.federation_agent.exports
        assert old_id not in exports and exports[new_id].policy.sample_period is not None

        # the rate follows: 20 Hz pushed, about 2 samples a second arrive now
        state = await until_state(
            http, url, lambda s: stream(s, "uav-a", "tracked-cars")["samples"] > 0
        )
        before = stream(state, "uav-a", "tracked-cars")["samples"]
        await asyncio.sleep(2.0)  # a measurement window, not a wait for an event
        async with http.get(url + "api/state") as r:
            after = stream(await r.json(), "uav-a", "tracked-cars")
        assert after["sample_period"] == 0.5
        assert 1 <= after["samples"] - before <= 7, after  # 20 Hz would be ~40

        bad = {
            "platform": {"platform": "uav-z", "label": "area", "sample_period": 1},
            "label": {"platform": "uav-a", "label": "weather", "sample_period": 1},
            "sample_period": {"platform": "uav-a", "label": "area", "sample_period": -1},
        }
        for key, body in bad.items():
            status, answer = await post(http, url + "api/policy", body)
            assert status == 400 and answer["error"].startswith(f"{key}: "), (key, answer)
        status, answer = await post(
            http, url + "api/policy", {"platform": "uav-a", "label": "area"}
        )
        assert status == 400 and answer["error"].startswith("sample_period: missing")
        # back to every sample
        body = {"platform": "uav-a", "label": "tracked-cars", "sample_period": None}
        status, answer = await post(http, url + "api/policy", body)
        assert status == 200 and answer["stream"]["sample_period"] is None


async def test_an_observation_enters_the_instance_and_the_map(demo_keys: Path) -> None:
    async with console_federation(demo_keys) as fed, client(fed) as http:
        url = fed.url
        body = {"x": 120.5, "y": 300, "text": "a car stopped on the bridge"}
        status, answer = await post(http, url + "api/observation", body)
        assert status == 200, answer
        assert answer["label"] == "observation"
        state = await until_state(http, url, lambda s: len(s["observations"]) == 1)
        assert state["observations"][0]["text"] == "a car stopped on the bridge"
        assert state["observations"][0]["x"] == 120.5
        # in the instance like any other sample: the operator's own stream, queryable
        latest = fed.operator.instance.latest("operator/observations").samples[0]
        assert latest.value == {"x": 120.5, "y": 300.0, "text": "a car stopped on the bridge"}
        status, answer = await post(
            http, url + "api/query", {"platform": "operator", "label": "observation"}
        )
        assert status == 200, answer
        assert answer["samples"][0]["value"]["text"] == "a car stopped on the bridge"
        # and the UAVs can ask for it too
        seen = await fed.uavs["uav-a"].platform.federation_agent.request_from(
            "operator", {"action": "get-latest", "labels": ["observation"]}, timeout=WAIT
        )
        assert seen["observation"]["samples"][0][0]["x"] == 120.5

        bad = {
            "x": {"x": "left", "y": 1, "text": "t"},
            "y": {"x": 1, "text": "t"},
            "text": {"x": 1, "y": 1, "text": "   "},
        }
        for key, b in bad.items():
            status, answer = await post(http, url + "api/observation", b)
            assert status == 400 and answer["error"].startswith(f"{key}: "), (key, answer)


async def test_a_refused_stream_is_shown_and_asked_again(
    demo_keys: Path, caplog: pytest.LogCaptureFixture
) -> None:
    async with console_federation(demo_keys) as fed, client(fed) as http:
        url = fed.url
        # a platform without the demo's streams joins: refused, shown, not fatal
        bare = await fed.start("uav-c", 2, streams=False)
        state = await until_state(
            http,
            url,
            lambda s: (
                any(p["name"] == "uav-c" for p in s["platforms"])
                and all(x["state"] == "refused" for x in platform(s, "uav-c")["streams"])
            ),
        )
        refused = stream(state, "uav-c", "tracked-cars")
        assert "tracked-cars" in refused["error"] and "no stream" in refused["error"]
        # said in the log too, where a view without a page (dyknow foxglove) shows it
        said = [r for r in caplog.records if "uav-c refused tracked-cars" in r.getMessage()]
        assert said and said[0].levelname == "WARNING", caplog.text
        assert filled(state, "uav-a")  # the others stream on
        # once it has them, the console's next attempt gets them
        uav = fed.uavs["uav-c"] = FakeUav(bare, 2)
        pusher = asyncio.create_task(uav.run(), name="test.push[uav-c]")
        try:
            await until_state(http, url, lambda s: filled(s, "uav-c"))
        finally:
            await _cancelled(pusher)


def test_console_refuses_a_nonsense_sample_period(demo_keys: Path) -> None:
    with pytest.raises(ValueError, match="sample_period"):
        OperatorConsole(FederationPlatform(config(demo_keys, "operator")), sample_period=0)


# -- any federation's labels --------------------------------------------------------------

WEATHER = {
    "name": "weather",
    "labels": {
        "temperature": "air temperature, degrees C",
        "wind": "wind speed (m/s) and direction (degrees)",
        "station-position": "where the station stands (x, y), metres",
    },
}
WEATHER_MAPPING = {
    "vocabulary": "weather",
    "labels": {"temperature": "sensor/t", "wind": "sensor/wind", "station-position": "self/pos"},
}


def weather_config(keys: Path, name: str, console: dict[str, Any] | None = None) -> PlatformConfig:
    """A platform of a weather federation: nothing of the traffic demo."""
    data: dict[str, Any] = {
        "name": name,
        "federation": "weather",
        "key": str(keys / "keys" / f"{name}.key"),
        "trust": str(keys / "trust.json"),
        "vocabulary": WEATHER,
        "mapping": WEATHER_MAPPING,
    }
    if console is not None:
        data["console"] = console
    return PlatformConfig.from_dict(data)


async def test_a_console_streams_and_serves_the_labels_its_config_names(tmp_path: Path) -> None:
    # a weather federation: its console streams what its [console] says, shows the
    # temperature and wind as they come, and draws the stations by their position
    pubs = [gen_keys(name, tmp_path / "keys")[2] for name in ("operator", "station-1")]
    trust_keys(tmp_path / "trust.json", pubs, federation="weather")
    streams = ["temperature", "wind", "station-position"]
    console = {"streams": streams, "roles": {"positions": "station-position"}}
    hub = MemoryHub()
    async with contextlib.AsyncExitStack() as stack:
        async with asyncio.timeout(WAIT):
            operator = await stack.enter_async_context(
                FederationPlatform(
                    weather_config(tmp_path, "operator", console),
                    transport=await stack.enter_async_context(hub.transport()),
                )
            )
            station = await stack.enter_async_context(
                FederationPlatform(
                    weather_config(tmp_path, "station-1"),
                    transport=await stack.enter_async_context(hub.transport()),
                )
            )
            sources = {
                label: station.instance.add_source(station.labels.to_local(label))
                for label in streams
            }
            fed = Federation(hub, tmp_path, operator)
            fed.console = await stack.enter_async_context(OperatorConsole(operator))

        async def weather() -> None:
            k = 0
            while True:
                k += 1
                sources["temperature"].push(20.0 + k % 3)
                sources["wind"].push({"speed": 4.5, "direction": 270})
                sources["station-position"].push({"x": 10.0, "y": 20.0})
                await asyncio.sleep(PUSH)

        pusher = asyncio.create_task(weather(), name="test.push[station-1]")
        stack.push_async_callback(_cancelled, pusher)
        http = await stack.enter_async_context(client(fed))

        def streaming(s: dict[str, Any]) -> bool:
            p = next((p for p in s["platforms"] if p["name"] == "station-1"), None)
            return p is not None and all(x["samples"] > 0 for x in p["streams"])

        await until_state(http, fed.url, streaming)
        async with http.get(fed.url + "api/state") as r:
            assert r.status == 200
            state = await r.json()
        assert state["streams"] == streams and state["roles"]["positions"] == "station-position"
        assert state["roles"]["tracks"] is None and state["observation_label"] is None
        s1 = platform(state, "station-1")
        assert [x["label"] for x in s1["streams"]] == streams
        assert all(x["state"] == "active" and x["export_id"] for x in s1["streams"])
        assert set(station.federation_agent.exports) == {x["export_id"] for x in s1["streams"]}
        by_label = {x["label"]: x for x in s1["streams"]}
        assert by_label["temperature"]["value"] in (20.0, 21.0, 22.0)
        assert by_label["wind"]["value"] == {"speed": 4.5, "direction": 270}
        assert by_label["station-position"]["value"] is None  # drawn: its position
        assert s1["position"] == {"x": 10.0, "y": 20.0}
        assert s1["area"] is None and s1["cars"] == [] and state["violations"] == []
        # a query names a weather label; a policy change takes one of the console's streams
        status, answer = await post(
            http, fed.url + "api/query", {"platform": "station-1", "label": "wind"}
        )
        assert status == 200 and answer["samples"][0]["value"]["speed"] == 4.5, answer
        body = {"platform": "station-1", "label": "tracked-cars", "sample_period": 1}
        status, answer = await post(http, fed.url + "api/policy", body)
        assert status == 400 and "temperature, wind, station-position" in answer["error"]
        # no 'observation' in this vocabulary: an observation stays local, shared under no label
        body = {"x": 1.0, "y": 2.0, "text": "fog"}
        status, answer = await post(http, fed.url + "api/observation", body)
        assert status == 200 and answer["label"] is None, answer


async def test_violations_of_several_labels_are_listed_together(tmp_path: Path) -> None:
    # a platform may publish each kind of violation under a label of its own (the deployed
    # UAVs' speeding): [console.roles] violations lists them, the console lists them as one
    pubs = [gen_keys(name, tmp_path / "keys")[2] for name in ("operator", "station-1")]
    trust_keys(tmp_path / "trust.json", pubs, federation="weather")
    alerts = {"gale": "winds over 20 m/s", "frost": "temperatures below 0 C"}
    vocab = {**WEATHER, "labels": {**WEATHER["labels"], **alerts}}
    mapping = {"vocabulary": "weather", "labels": {label: f"alerts/{label}" for label in alerts}}

    def weather(name: str, console: dict[str, Any] | None = None) -> PlatformConfig:
        data = {**weather_config(tmp_path, name, console).model_dump(), "vocabulary": vocab}
        return PlatformConfig.from_dict({**data, "mapping": mapping})

    console = {"streams": ["gale", "frost"], "roles": {"violations": ["gale", "frost"]}}
    hub = MemoryHub()
    async with contextlib.AsyncExitStack() as stack:
        async with asyncio.timeout(WAIT):
            operator = await stack.enter_async_context(
                FederationPlatform(
                    weather("operator", console),
                    transport=await stack.enter_async_context(hub.transport()),
                )
            )
            station = await stack.enter_async_context(
                FederationPlatform(
                    weather("station-1"), transport=await stack.enter_async_context(hub.transport())
                )
            )
            fed = Federation(hub, tmp_path, operator)
            fed.console = await stack.enter_async_context(OperatorConsole(operator))
        gale, frost = (station.instance.add_source(f"alerts/{label}") for label in alerts)

        async def alarms() -> None:
            while True:
                gale.push({"kind": "gale", "speed": 24.0, "x": 1.0, "y": 2.0})
                frost.push({"kind": "frost", "temperature": -3.0})
                await asyncio.sleep(PUSH)

        pusher = asyncio.create_task(alarms(), name="test.push[station-1]")
        stack.push_async_callback(_cancelled, pusher)
        http = await stack.enter_async_context(client(fed))

        def both(s: dict[str, Any]) -> bool:
            return {v["kind"] for v in s["violations"]} == {"gale", "frost"}

        state = await until_state(http, fed.url, both)
        assert state["roles"]["violations"] == ["gale", "frost"]
        kinds = {v["kind"]: v for v in state["violations"]}
        assert set(kinds) == {"gale", "frost"}
        assert all(v["reported-by"] == "station-1" for v in kinds.values())
        assert kinds["gale"]["speed"] == 24.0 and kinds["frost"]["temperature"] == -3.0
        # drawn as violations: neither kept as a stream's latest value
        s1 = platform(state, "station-1")
        assert [x["value"] for x in s1["streams"]] == [None, None]
    # a single label is still one string; a listed label must be one of the streams
    one = ConsoleSettings(streams=("gale",), roles={"violations": "gale"})
    assert one.roles.violations == "gale" and one.roles.assigned() == [("violations", "gale")]
    with pytest.raises(ValueError, match="violations = 'frost' is not one of streams"):
        ConsoleSettings(streams=("gale",), roles={"violations": ["gale", "frost"]})


async def test_a_console_of_no_streams_follows_the_members_only(demo_keys: Path) -> None:
    # no [console] streams: nothing is asked of anyone (no label is built in)
    cfg = config(demo_keys, "operator").model_copy(
        update={"console": ConsoleSettings(allow_hosts=("operator.test",))}
    )
    hub = MemoryHub()
    async with contextlib.AsyncExitStack() as stack:
        async with asyncio.timeout(WAIT):
            t = await stack.enter_async_context(hub.transport())
            operator = await stack.enter_async_context(FederationPlatform(cfg, transport=t))
            fed = Federation(hub, demo_keys, operator)
            stack.push_async_callback(fed.aclose)
            uav = await fed.start("uav-a", 0)
            fed.console = await stack.enter_async_context(OperatorConsole(operator))
        http = await stack.enter_async_context(client(fed))
        state = await until_state(
            http, fed.url, lambda s: any(p["name"] == "uav-a" for p in s["platforms"])
        )
        assert state["streams"] == [] and platform(state, "uav-a")["streams"] == []
        assert uav.federation_agent.exports == {}


def test_a_console_section_is_checked_against_the_vocabulary(demo_keys: Path) -> None:
    # [console] names the federation's labels: one of another federation is named at start
    bad = {**console_config(), "streams": [*STREAM_LABELS, "temperature"]}
    data = {**config(demo_keys, "operator").model_dump(), "console": bad}
    with pytest.raises(PlatformConfigError, match=r"console\.streams: 'temperature' is not"):
        FederationPlatform(PlatformConfig.from_dict(data, source="operator.toml"))
    with pytest.raises(ValueError, match=r"console\.streams: 'temperature' is not"):
        OperatorConsole(
            FederationPlatform(config(demo_keys, "operator")),
            settings=ConsoleSettings(streams=("temperature",)),
        )


# -- what another site's page, a local process or a platform's numbers cannot do ----------


async def test_a_page_of_another_site_cannot_post_to_the_console(demo_keys: Path) -> None:
    # text/plain needs no CORS preflight: a page the operator opens could otherwise
    # change policies or inject observations
    async with console_federation(demo_keys) as fed, client(fed) as http:
        body = json.dumps({"x": 1.0, "y": 2.0, "text": "fake"})
        async with http.post(
            fed.url + "api/observation", data=body, headers={"Content-Type": "text/plain"}
        ) as r:
            assert r.status == 400 and "Content-Type" in (await r.json())["error"]
        async with http.post(
            fed.url + "api/policy",
            data=json.dumps({"platform": "uav-a", "label": "area", "sample_period": 86400}),
            headers={"Content-Type": "application/json", "Origin": "http://evil.example"},
        ) as r:
            assert r.status == 403 and "Origin" in (await r.json())["error"]
        status, _ = await post(http, fed.url + "api/observation", {"x": 1, "y": 2, "text": "ok"})
        assert status == 200  # the console's own page (same origin, or none) still may


async def test_a_rebinding_page_or_a_local_process_cannot_change_a_policy(
    demo_keys: Path,
) -> None:
    # issue 11's attack: Host and Origin evil.example (a name rebound to 127.0.0.1), or
    # a local process without the token, cancelled and re-created uav-a's export
    async with console_federation(demo_keys) as fed, client(fed) as http:
        state = await until_state(http, fed.url, lambda s: filled(s, "uav-a"))
        before = stream(state, "uav-a", "tracked-cars")["export_id"]
        exports = fed.uavs["uav-a"].platform.federation_agent.exports
        body = json.dumps({"platform": "uav-a", "label": "tracked-cars", "sample_period": 60})
        port = fed.url.rsplit(":", 1)[1].strip("/")
        evil = {"Host": f"evil.example:{port}", "Origin": f"http://evil.example:{port}"}
        assert fed.console is not None
        attempts = [
            ({**evil, "Authorization": f"Bearer {fed.console.token}"}, 403, "Host"),
            (evil, 403, "Host"),
            ({}, 401, "token"),
            ({"Authorization": "Bearer " + "x" * 32}, 403, "token"),
        ]
        async with aiohttp.ClientSession() as bare:  # no token of its own
            for headers, status, word in attempts:
                for path, data in (("api/policy", body), ("api/state", None)):
                    method = bare.post if data else bare.get
                    async with method(
                        fed.url + path,
                        data=data,
                        headers={"Content-Type": "application/json", **headers},
                    ) as r:
                        answer = await r.json()
                        assert r.status == status and word in answer["error"], (headers, answer)
                        assert "platforms" not in answer  # nothing of the state leaked
        assert set(exports) >= {before}  # the export was never cancelled nor re-created
        async with http.get(fed.url + "api/state") as r:
            assert stream(await r.json(), "uav-a", "tracked-cars")["export_id"] == before
        async with http.get(fed.url + "api/stats") as r:
            stats = await r.json()
        assert stats["refused"] == {"host": 4, "origin": 0, "no-token": 2, "bad-token": 2}
        audit = [r for r in fed.operator.interface.audit.records if r.get("stage") == "console"]
        assert [r["refusal"] for r in audit] == ["host"] * 4 + ["no-token"] * 2 + ["bad-token"] * 2
        assert all(r["verdict"] == "refused" and r["platform"] == "operator" for r in audit)
        assert audit[0]["host"] == f"evil.example:{port}" and audit[0]["path"] == "/api/policy"


async def test_a_non_finite_number_from_a_platform_does_not_break_the_page(demo_keys: Path) -> None:
    async with console_federation(demo_keys) as fed, client(fed) as http:
        # a stream is followed from its agreement on: a violation pushed before uav-a
        # exports it is never sent (on a loaded machine the console asks that late)
        await until_state(
            http, fed.url, lambda s: stream(s, "uav-a", "violation")["state"] == "active"
        )
        fed.uavs["uav-a"].violations.append(
            {"kind": "turn", "car": "c", "other": None, "x": float("nan"), "y": float("inf")}
        )
        state = await until_state(http, fed.url, lambda s: bool(s["violations"]))
        assert state["violations"][0]["x"] is None and state["violations"][0]["y"] is None
        async with http.get(fed.url + "api/state") as r:
            text = await r.text()
        assert "NaN" not in text and "Infinity" not in text
        json.loads(text)  # what the page's JSON.parse reads


async def test_a_stream_its_live_platform_stops_is_asked_for_again(demo_keys: Path) -> None:
    # the export's lease runs out (the operator froze longer than it) while both stay up
    async with console_federation(demo_keys) as fed, client(fed) as http:
        await until_state(http, fed.url, lambda s: filled(s, "uav-a"))
        first = stream(await until_state(http, fed.url, lambda s: True), "uav-a", "tracked-cars")
        uav = fed.uavs["uav-a"].platform
        old = next(e for e in uav.exporter.exports() if e.semantic_label == "tracked-cars")
        old.last_heard -= 3600  # the proxy's own lease path: no report for an hour
        state = await until_state(
            http,
            fed.url,
            lambda s: (
                stream(s, "uav-a", "tracked-cars")["state"] == "active"
                and stream(s, "uav-a", "tracked-cars")["export_id"] != first["export_id"]
            ),
        )
        assert old.ended is not None and old.ended.startswith("lease-expired")
        assert platform(state, "uav-a")["state"] == "alive"
        assert any(e.semantic_label == "tracked-cars" for e in uav.exporter.exports())


async def test_a_console_stops_promptly_when_no_provider_answers(demo_keys: Path) -> None:
    # deploy/local/down: the router goes while the console still follows streams; the
    # cancels it sends on closing are never answered, and must not hold its stop
    async with console_federation(demo_keys) as fed, client(fed) as http:
        state = await until_state(http, fed.url, lambda s: all(filled(s, n) for n in UAVS))
        assert all(s["export_id"] for n in UAVS for s in platform(state, n)["streams"])

        async def lost(*args: Any, **kwargs: Any) -> None:
            return None

        def lost_now(*args: Any, **kwargs: Any) -> None:
            return None

        fed.operator.transport.publish = lost  # type: ignore[method-assign]
        # what waits for nothing goes out without `publish` (`InterfaceAgent.send_now`)
        fed.operator.transport.publish_nowait = lost_now  # type: ignore[method-assign]
        assert fed.console is not None
        started = asyncio.get_running_loop().time()
        await fed.console.aclose()
        assert asyncio.get_running_loop().time() - started < 5.0


async def test_a_stream_agreed_after_a_refusal_is_said_as_the_refusal_was(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The refusal is a warning in the console's log; its end (a sharing rule added) too."""
    from types import SimpleNamespace

    from federation import _follow
    from federation._follow import FollowedStream

    answers: list[Any] = [RuntimeError("label 's1-incident' may not be streamed to tmc"), "x-1"]

    async def create_stream(member: str, labels: list[str], **_: Any) -> str:
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return str(answer)

    platform = SimpleNamespace(
        name="tmc", federation_agent=SimpleNamespace(create_stream=create_stream)
    )
    monkeypatch.setattr(_follow, "RETRY", 0.01)
    stream = FollowedStream("s1-incident")
    with caplog.at_level("WARNING", logger="federation.follow"):
        await asyncio.wait_for(
            _follow._ask_for(platform, "roadside", stream, lambda: True, lambda: None),  # type: ignore[arg-type]
            5,
        )
    warned = [r.getMessage() for r in caplog.records]
    assert warned[0].startswith("roadside refused s1-incident to tmc: label 's1-incident'")
    assert warned[1:] == ["roadside now streams s1-incident to tmc (refused before)"]
    assert stream.state == "active" and stream.export_id == "x-1"


async def test_a_refused_stream_a_policy_change_gets_is_said_as_agreed_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The page's policy change on a refused stream, agreed: said as the retry's agreement
    is; and once only: asked again later, it was not refused since it flowed."""
    from types import SimpleNamespace

    from federation import _follow
    from federation.console._server import _Platform, _Stream

    answers: list[Any] = [RuntimeError("label 's1-incident' may not be streamed to tmc"), "x-1"]
    answers += ["x-2"]

    async def create_stream(member: str, labels: list[str], **_: Any) -> str:
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return str(answer)

    async def cancel_stream(member: str, export_id: str, **_: Any) -> None:
        return None

    agent = SimpleNamespace(create_stream=create_stream, cancel_stream=cancel_stream)
    platform = SimpleNamespace(name="tmc", federation_agent=agent)
    console = SimpleNamespace(platform=platform, _changed=lambda: None)
    stream = _Stream("s1-incident")
    with caplog.at_level("WARNING", logger="federation.follow"):
        # refused once (the retry loop's first ask), then the page asks for another period
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(
                _follow._ask_for(platform, "roadside", stream, lambda: True, lambda: None),  # type: ignore[arg-type]
                0.2,
            )
        assert stream.state == "refused" and stream.refused_before
        roadside = _Platform("roadside")
        await OperatorConsole._change_policy(console, roadside, stream, 0.5)  # type: ignore[arg-type]
        assert stream.state == "active" and stream.export_id == "x-1"
        assert not stream.refused_before
        # the export ends (its lease expired) and the follower asks again: agreed, not news
        stream.export_id, stream.state = None, "requesting"
        await asyncio.wait_for(
            _follow._ask_for(platform, "roadside", stream, lambda: True, lambda: None),  # type: ignore[arg-type]
            5,
        )
    warned = [r.getMessage() for r in caplog.records]
    assert warned[0].startswith("roadside refused s1-incident to tmc: label 's1-incident'")
    assert warned[1:] == ["roadside now streams s1-incident to tmc (refused before)"]
    assert stream.state == "active" and stream.export_id == "x-2"


def test_a_value_that_does_not_fit_its_role_is_logged_without_what_it_says(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A sample the console cannot draw is logged by kind only: neither the value nor the
    error's text (which quotes it) is in the log, as it came encrypted from its platform;
    it is skipped and the next one drawn."""
    from types import SimpleNamespace

    from federation._follow import BadValues
    from federation.console._server import _Platform, _Stream

    secret = f"said-in-confidence-{os.urandom(8).hex()}"
    bad = BadValues(logging.getLogger("federation.console"))
    console = SimpleNamespace(_changed=lambda: None, _bad=bad)
    console._apply = lambda *args: OperatorConsole._apply(console, *args)  # type: ignore[arg-type]
    uav = _Platform("uav-a")
    stream = _Stream("uav-a-position", role="positions")
    batch = [({"x": secret, "y": 1.0}, 1, 1), ({"x": 2.0, "y": 3.0}, 2, 2)]
    with caplog.at_level("DEBUG", logger="federation"):
        OperatorConsole._take(console, uav, stream, batch)  # type: ignore[arg-type]
    assert secret not in caplog.text
    said = [r.getMessage() for r in caplog.records if "bad value" in r.getMessage()]
    assert said == ["console: uav-a uav-a-position: bad value (dict): ValueError"]
    assert uav.position == {"x": 2.0, "y": 3.0} and stream.samples == 2


async def test_a_member_sending_bad_values_fast_is_counted_and_logged_bounded(
    demo_keys: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A member whose violations stream sends 2000 values that are not objects at about
    1 kHz, over its real export: each is counted (``/api/stats``), but the log has the
    first and then at most one line per interval, each saying how many it stands for,
    and the close says the rest: every one is accounted for, none quoted."""
    import re
    import time

    from federation import _follow

    interval = 0.25
    monkeypatch.setattr(_follow, "BAD_VALUE_LOG_INTERVAL", interval)
    n = 2000
    secret = f"said-in-confidence-{os.urandom(8).hex()}"

    def bad_lines() -> list[str]:
        return [r.getMessage() for r in caplog.records if "bad value" in r.getMessage()]

    with caplog.at_level("WARNING", logger="federation.console"):
        async with console_federation(demo_keys) as fed, client(fed) as http:
            await until_state(http, fed.url, lambda s: filled(s, "uav-a"))
            source = fed.uavs["uav-a"].sources["violation"]
            began = time.monotonic()
            for i in range(n):
                source.push(f"{secret} {i}")  # not an object: no violation
                if i % 10 == 9:
                    await asyncio.sleep(0.01)  # paced as a 1 kHz sender, not one batch
            await until_state(
                http, fed.url, lambda s: stream(s, "uav-a", "violation")["samples"] >= n
            )
            took = time.monotonic() - began
            async with http.get(fed.url + "api/stats") as r:
                stats = await r.json()
            assert stats["bad_values"] == {"uav-a/violation": n}
            assert stats["bad_values_total"] == n
            during = bad_lines()
    said = bad_lines()
    assert secret not in caplog.text
    assert said[0] == "console: uav-a violation: bad value (str): TypeError"
    assert 2 <= len(during) <= 2 + took / interval, (took, during)  # bounded, yet said on
    assert len(said) == len(during) + 1  # the close: what was held since the last line
    assert said[-1].startswith("console: uav-a violation: ")
    assert said[-1].endswith(f"more bad values held back, the latest (str): TypeError; {n} in all")
    stood_for = 0
    for line in said:
        before = re.search(r"\(and (\d+) more held back before it; (\d+) in all\)$", line)
        held = re.search(r": (\d+) more bad values held back", line)
        stood_for += int(before[1]) + 1 if before else int(held[1]) if held else 1
        if before:
            assert int(before[2]) == stood_for
    assert stood_for == n


async def test_a_members_long_refusal_is_kept_bounded_on_one_line(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The refusal the page and /api/state show is a member's word: on one line, capped as
    a log line quotes it (`quoted`); refused alike again, it is not news."""
    from types import SimpleNamespace

    from agents._agent import Refused
    from federation import _follow
    from federation._quote import QUOTE_MAX
    from federation.console._server import _Stream

    # a member may write anything in its refusal: 100 kB, a forged line, a terminal escape
    content = "no\nINFO forged line \x1b[2J" + "x" * 100_000
    refusal = Refused("refused", SimpleNamespace(content=content))  # type: ignore[arg-type]
    asked: list[str] = []

    async def create_stream(member: str, labels: list[str], **_: Any) -> str:
        asked.append(member)
        if len(asked) < 3:
            raise refusal
        return "x-1"

    platform = SimpleNamespace(
        name="tmc", federation_agent=SimpleNamespace(create_stream=create_stream)
    )
    monkeypatch.setattr(_follow, "RETRY", 0.01)
    stream = _Stream("s1-incident")
    shown: list[Any] = []
    with caplog.at_level("INFO", logger="federation.follow"):
        await asyncio.wait_for(
            _follow._ask_for(
                platform,  # type: ignore[arg-type]
                "roadside",
                stream,
                lambda: True,
                lambda: shown.append(stream.to_json(0.0)["error"]),
            ),
            5,
        )
    whole = f"refused: {content}"
    error = shown[0]
    assert error == shown[1]
    assert error.startswith("refused: no\\x0aINFO forged line \\x1b[2Jxxx")
    # 200 characters shown, two of them escaped to four: 194 of the member's kept
    assert error.endswith(f"… ({len(whole)} characters, {len(whole) - 194} left out)"), error
    assert len(error.partition("…")[0]) == QUOTE_MAX and error.isprintable()
    # the second refusal, the same, is said at info only: the kept text still compares
    levels = [r.levelname for r in caplog.records if "refused s1-incident" in r.getMessage()]
    assert levels == ["WARNING", "INFO"]
    assert shown[2] is None and stream.state == "active"
