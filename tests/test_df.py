"""Directory Facilitator: local registry, visibility, subscriptions, the global view."""

from __future__ import annotations

import asyncio
import contextlib
import re
import secrets
import signal
import subprocess
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import orjson
import pytest

from agents import (
    FIPA_AGENT_MANAGEMENT,
    Agent,
    AgentPlatform,
    DirectoryEvent,
    InterfaceAgent,
    KeyPair,
    MemoryHub,
    NotUnderstood,
    Refused,
    ServiceDescription,
    ServiceError,
    ServiceQuery,
    TrustStore,
    Visibility,
    deregister_service,
    modify_service,
    register_service,
    request,
    search_services,
    subscribe,
    subscribe_services,
    visibility_allows,
)
from agents.transports import MqttConfig, MqttTransport, Subscription

V = Visibility


@contextlib.asynccontextmanager
async def platforms(
    *names: str, hub: MemoryHub | None = None
) -> AsyncIterator[list[AgentPlatform]]:
    """Platforms on one in-memory hub; on exit, checks that nothing is left behind."""
    hub = hub or MemoryHub()
    async with contextlib.AsyncExitStack() as stack:
        out = []
        for name in names:
            transport = await stack.enter_async_context(hub.transport())
            out.append(
                await stack.enter_async_context(AgentPlatform(name, transport, federation="t"))
            )
        yield out
    assert asyncio.all_tasks() == {asyncio.current_task()}
    assert not hub.subscribers and not hub.queryables and not hub.tokens and not hub.watchers


def svc(
    provider: str, name: str, visibility: V = V.PUBLIC, type: str = "camera", **props: Any
) -> ServiceDescription:
    return ServiceDescription(
        name=name, type=type, provider=provider, properties=props, visibility=visibility
    )


async def wait_for(
    sub: Subscription[DirectoryEvent], pred: Callable[[DirectoryEvent], bool]
) -> DirectoryEvent:
    """The first event ``pred`` accepts (the caller bounds the wait)."""
    async for event in sub:
        if pred(event):
            return event
    raise AssertionError("the watch ended")


def names(services: list[ServiceDescription]) -> list[str]:
    return sorted(s.name for s in services)


# -- local registry (Python API) ------------------------------------------------------------


async def test_register_search_modify_deregister() -> None:
    async with asyncio.timeout(5), platforms("uav-a") as [p]:
        df = p.df
        assert df is not None
        cam = svc("cam@uav-a", "front", resolution=1080, color=True)
        await df.register(cam)
        await df.register(svc("cam@uav-a", "rear", resolution=720))
        await df.register(svc("lidar@uav-a", "scan", type="lidar", range=100))
        assert names(df.search()) == ["front", "rear", "scan"]
        assert names(df.search(type="camera")) == ["front", "rear"]
        assert names(df.search(name="scan")) == ["scan"]
        assert names(df.search(properties={"resolution": 1080})) == ["front"]
        assert names(df.search({"properties": {"resolution": 720}, "type": "camera"})) == ["rear"]
        assert names(df.search(ServiceQuery(provider="cam@uav-a"))) == ["front", "rear"]
        assert df.search(properties={"resolution": 1080, "zoom": 2}) == []  # subset, not overlap
        await df.modify(cam.model_copy(update={"properties": {"resolution": 4000}}))
        assert names(df.search(properties={"resolution": 4000})) == ["front"]
        assert await df.deregister("cam@uav-a", "front") == [
            cam.model_copy(update={"properties": {"resolution": 4000}})
        ]
        assert names(df.search()) == ["rear", "scan"]
        assert len(await df.deregister("cam@uav-a")) == 1  # all of its services
        assert names(df.search()) == ["scan"]
        assert await df.deregister("cam@uav-a") == []


async def test_search_by_ontology_and_protocol() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        assert p.df is not None
        await p.df.register(
            ServiceDescription(
                name="s",
                type="t",
                provider="x@p",
                ontology="dyknow",
                protocols=["fipa-request", "fipa-subscribe"],
            )
        )
        assert names(p.df.search(ontology="dyknow", protocol="fipa-subscribe")) == ["s"]
        assert p.df.search(protocol="fipa-contract-net") == []
        assert p.df.search(ontology="other") == []


async def test_registry_errors() -> None:
    async with asyncio.timeout(5), platforms("uav-a") as [p]:
        df = p.df
        assert df is not None
        await df.register(svc("cam@uav-a", "front"))
        with pytest.raises(ServiceError, match="already"):
            await df.register(svc("cam@uav-a", "front"))
        with pytest.raises(ServiceError, match="not an agent of platform uav-a"):
            await df.register(svc("cam@uav-b", "front"))
        with pytest.raises(ServiceError, match="no service"):
            await df.modify(svc("cam@uav-a", "side"))
        with pytest.raises(ValueError):
            svc("not-an-id", "x")
        with pytest.raises(ValueError):
            ServiceQuery.model_validate({"colour": "red"})


# -- visibility ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("visibility", "asker", "via_interface", "allowed"),
    [
        (V.PUBLIC, "uav-a", False, True),
        (V.PROTECTED, "uav-a", False, True),
        (V.PRIVATE, "uav-a", False, True),
        (V.PUBLIC, "uav-b", False, True),
        (V.PUBLIC, "uav-b", True, True),
        (V.PROTECTED, "uav-b", False, False),
        (V.PROTECTED, "uav-b", True, True),
        (V.PRIVATE, "uav-b", False, False),
        (V.PRIVATE, "uav-b", True, False),
    ],
)
def test_visibility_rule(visibility: V, asker: str, via_interface: bool, allowed: bool) -> None:
    assert visibility_allows(svc("x@uav-a", "s", visibility), asker, via_interface) is allowed


async def test_search_shows_each_asker_what_it_may_see() -> None:
    async with asyncio.timeout(5), platforms("uav-a") as [p]:
        df = p.df
        assert df is not None
        for v in V:
            await df.register(svc("cam@uav-a", v.value, v))
        assert names(df.search()) == ["private", "protected", "public"]  # local code
        assert names(df.search(asker_platform="uav-a")) == ["private", "protected", "public"]
        assert names(df.search(asker_platform="uav-b", via_interface=True)) == [
            "protected",
            "public",
        ]
        assert names(df.search(asker_platform="uav-b")) == ["public"]


async def test_access_control_lookups_for_the_interface_agent() -> None:
    async with asyncio.timeout(5), platforms("uav-a") as [p]:
        df = p.df
        assert df is not None
        await df.register(svc("pub@uav-a", "s1", V.PUBLIC))
        await df.register(svc("prot@uav-a", "s2", V.PROTECTED))
        await df.register(svc("priv@uav-a", "s3", V.PRIVATE))
        await df.register(svc("mixed@uav-a", "hidden", V.PRIVATE))
        await df.register(svc("mixed@uav-a", "shown", V.PUBLIC))
        assert names(df.services_of_agent("mixed@uav-a")) == ["hidden", "shown"]
        assert df.service_of_agent("mixed@uav-a", "shown") is not None
        assert df.service_of_agent("mixed@uav-a", "nope") is None
        assert df.services_of_agent("nobody@uav-a") == []
        assert df.reachable("pub@uav-a", "uav-b", via_interface=False)
        assert df.reachable("prot@uav-a", "uav-b")
        assert not df.reachable("prot@uav-a", "uav-b", via_interface=False)
        assert not df.reachable("priv@uav-a", "uav-b")
        assert df.reachable("mixed@uav-a", "uav-b")
        assert not df.reachable("nobody@uav-a", "uav-b")
        assert df.reachable("priv@uav-a", "uav-a")  # local agents reach everyone
        assert df.reachable("df@uav-a", "uav-b")  # the DF answers searches from anywhere


async def test_access_lookups_remember_only_agents_that_offer_services() -> None:
    """Names another platform invents (up to a message long) are answered, not remembered.

    The answers kept are per provider registered here: a platform asking for agents that
    offer nothing cannot fill the DF's memory with its names, nor push out what it keeps.
    """
    async with asyncio.timeout(5), platforms("uav-a") as [p]:
        df = p.df
        assert df is not None
        await df.register(svc("pub@uav-a", "s1", V.PUBLIC))
        assert df.reachable("pub@uav-a", "uav-b")
        for i in range(50):
            name = f"{i:04d}" + "x" * 100_000 + "@uav-a"  # a valid, very long identifier
            assert not df.reachable(name, "uav-b")
            assert df.reachable(name, "uav-a")  # local agents reach everyone
        assert df.reachable("df@uav-a", "uav-b")
        kept = df._reach
        assert all(receiver in ("pub@uav-a", "df@uav-a") for receiver, _, _ in kept)
        assert sum(len(receiver) for receiver, _, _ in kept) < 100


# -- the ACL face --------------------------------------------------------------------------


async def test_acl_register_search_modify_deregister() -> None:
    async with asyncio.timeout(5), platforms("uav-a", "uav-b") as [pa, pb]:
        cam = await pa.add(Agent("cam"))
        await register_service(cam, svc("cam@uav-a", "front", V.PUBLIC, resolution=1080))
        await register_service(cam, svc("cam@uav-a", "rear", V.PROTECTED))
        await register_service(cam, svc("cam@uav-a", "debug", V.PRIVATE))
        assert names(await search_services(cam)) == ["debug", "front", "rear"]
        assert names(
            await search_services(cam, type="camera", properties={"resolution": 1080})
        ) == ["front"]
        remote = await pb.add(Agent("remote"))
        # From another platform (through its channel): public and protected only.
        assert names(await search_services(remote, df="df@uav-a")) == ["front", "rear"]
        await modify_service(cam, svc("cam@uav-a", "rear", V.PRIVATE))
        assert names(await search_services(remote, df="df@uav-a")) == ["front"]
        assert await deregister_service(cam, "front") == 1
        assert await deregister_service(cam) == 2
        assert await search_services(cam) == []


async def test_acl_refusals() -> None:
    async with asyncio.timeout(5), platforms("uav-a", "uav-b") as [pa, pb]:
        cam = await pa.add(Agent("cam"))
        other = await pa.add(Agent("other"))
        remote = await pb.add(Agent("remote"))
        with pytest.raises(Refused, match="only register its own"):
            await register_service(other, svc("cam@uav-a", "front"))
        with pytest.raises(Refused, match="not an agent of platform uav-a"):
            await register_service(remote, svc("remote@uav-b", "x"), df="df@uav-a")
        await register_service(cam, svc("cam@uav-a", "front"))
        with pytest.raises(Refused, match="already"):
            await register_service(cam, svc("cam@uav-a", "front"))
        with pytest.raises(Refused, match="no service"):
            await deregister_service(cam, "ghost")
        with pytest.raises(Refused, match="no service"):
            await modify_service(cam, svc("cam@uav-a", "ghost"))
        df = "df@uav-a"
        onto = FIPA_AGENT_MANAGEMENT
        for content, says in [
            ({"action": "teleport"}, "unsupported function"),
            ("register", "action"),
            ({"action": "register", "service": {"name": "x"}}, "invalid"),
            ({"action": "search", "query": {"colour": "red"}}, "invalid"),
            ({"action": "search", "scope": "galaxy"}, "unknown scope"),
            ({"action": "deregister", "name": 5}, "string"),
        ]:
            with pytest.raises(Refused, match=says):
                await request(cam, df, content, ontology=onto)
        with pytest.raises(NotUnderstood):
            await request(cam, df, {"action": "search"}, ontology="not-the-df-ontology")
        assert names(await search_services(cam)) == ["front"]  # nothing above changed it


# -- watching changes ----------------------------------------------------------------------


async def test_python_watch_sees_every_local_change() -> None:
    async with asyncio.timeout(5), platforms("uav-a") as [p]:
        df = p.df
        assert df is not None
        async with df.watch() as changes:
            s = svc("cam@uav-a", "front", V.PRIVATE)
            await df.register(s)
            await df.modify(s.model_copy(update={"type": "thermal"}))
            await df.deregister("cam@uav-a")
            got = [await changes.get(timeout=2) for _ in range(3)]
        assert [(e.op, e.platform, e.service.type if e.service else None) for e in got] == [
            ("register", "uav-a", "camera"),
            ("modify", "uav-a", "thermal"),
            ("deregister", "uav-a", "thermal"),
        ]


async def test_a_stopped_agent_s_services_are_deregistered() -> None:
    async with asyncio.timeout(5), platforms("uav-a") as [p]:
        df = p.df
        assert df is not None
        cam = await p.add(Agent("cam"))
        await df.register(svc("cam@uav-a", "front"))
        async with df.watch() as changes:
            await cam.stop()
            assert df.search() == []  # at once
            event = await changes.get(timeout=2)
        assert (event.op, event.service and event.service.name) == ("deregister", "front")


async def test_fipa_subscribe_to_the_df_respects_visibility() -> None:
    async with asyncio.timeout(5), platforms("uav-a", "uav-b") as [pa, pb]:
        df = pa.df
        assert df is not None
        local = await pa.add(Agent("local"))
        remote = await pb.add(Agent("remote"))
        local_stream = await subscribe_services(local)
        remote_stream = await subscribe_services(remote, df="df@uav-a", type="camera")
        await df.register(svc("cam@uav-a", "secret", V.PRIVATE))
        await df.register(svc("lidar@uav-a", "scan", V.PUBLIC, type="lidar"))  # not a camera
        await df.register(svc("cam@uav-a", "front", V.PUBLIC))
        await df.modify(svc("cam@uav-a", "front", V.PRIVATE))  # hidden from uav-b now
        local_events = [await local_stream.get(timeout=2) for _ in range(4)]
        assert [(e["op"], e["service"]["name"]) for e in local_events] == [  # type: ignore[index, call-overload]
            ("register", "secret"),
            ("register", "scan"),
            ("register", "front"),
            ("modify", "front"),
        ]
        remote_events = [await remote_stream.get(timeout=2) for _ in range(2)]
        assert [(e["op"], e["service"]["name"]) for e in remote_events] == [  # type: ignore[index, call-overload]
            ("register", "front"),
            ("deregister", "front"),  # it became private: gone, as far as uav-b may know
        ]
        await remote_stream.cancel()
        await local_stream.cancel()
        with pytest.raises(ValueError):  # checked before it is sent
            await subscribe_services(local, {"colour": "red"})
        with pytest.raises(Refused, match="invalid query"):  # and by the DF
            await subscribe(local, "df@uav-a", {"colour": "red"}, ontology=FIPA_AGENT_MANAGEMENT)


# -- the global directory ------------------------------------------------------------------


async def test_global_view_across_three_platforms() -> None:
    async with asyncio.timeout(5), platforms("uav-a", "uav-b", "operator") as ps:
        views = [p.global_df for p in ps]
        assert all(v is not None for v in views)
        watches = [v.watch() for v in views if v is not None]
        for p in ps:
            assert p.df is not None
            await p.df.register(svc(f"cam@{p.name}", "public-cam", V.PUBLIC, site=p.name))
            await p.df.register(svc(f"cam@{p.name}", "protected-cam", V.PROTECTED))
            await p.df.register(svc(f"cam@{p.name}", "private-cam", V.PRIVATE))
        for w in watches:  # each view learns the three public services, its own included
            seen = set()
            while len(seen) < 3:
                e = await w.get(timeout=2)
                if e.op == "register" and e.service is not None:
                    seen.add(e.service.provider)
        for v in views:
            assert v is not None
            assert sorted(s.provider for s in v.services()) == [
                "cam@operator",
                "cam@uav-a",
                "cam@uav-b",
            ]
            assert {s.name for s in v.services()} == {"public-cam"}
            assert v.platforms == ["operator", "uav-a", "uav-b"]
            assert [s.provider for s in v.search(properties={"site": "uav-b"})] == ["cam@uav-b"]
        # Deregistering and hiding on one platform updates the others' views.
        pa, pb, _ = ps
        assert pa.df is not None and pb.df is not None
        await pa.df.deregister("cam@uav-a", "public-cam")
        await pb.df.modify(svc("cam@uav-b", "public-cam", V.PRIVATE))
        for w in watches:
            e1 = await wait_for(w, lambda e: e.op == "deregister")
            e2 = await wait_for(w, lambda e: e.op == "deregister")
            assert {e1.platform, e2.platform} == {"uav-a", "uav-b"}
        for v in views:
            assert v is not None
            assert [s.provider for s in v.services()] == ["cam@operator"]
        # And a global search over ACL sees the same.
        asker = await pa.add(Agent("asker"))
        assert [s.provider for s in await search_services(asker, scope="global")] == [
            "cam@operator"
        ]
        for w in watches:
            w.close()


async def test_a_platform_joining_later_gets_the_snapshot() -> None:
    hub = MemoryHub()
    async with asyncio.timeout(5), platforms("uav-a", "uav-b", hub=hub) as [pa, pb]:
        assert pa.df is not None and pb.df is not None and pa.global_df is not None
        await pa.df.register(svc("cam@uav-a", "cam", V.PUBLIC))
        await pb.df.register(svc("cam@uav-b", "cam", V.PROTECTED))  # not global
        async with pa.global_df.watch() as w:
            async with hub.transport() as t, AgentPlatform("late", t, federation="t") as late:
                assert late.global_df is not None
                # Built from the query of df/* while entering: no waiting needed.
                assert [s.provider for s in late.global_df.services()] == ["cam@uav-a"]
                assert late.global_df.platforms == ["late", "uav-a", "uav-b"]
            await wait_for(w, lambda e: e == DirectoryEvent("platform-gone", "late", None))
        assert pa.global_df.platforms == ["uav-a", "uav-b"]


async def test_a_platform_that_dies_disappears_from_the_others_views() -> None:
    hub = MemoryHub()
    async with asyncio.timeout(5), platforms("uav-a", "uav-b", "uav-c", hub=hub) as [pa, pb, pc]:
        assert pa.global_df is not None and pb.global_df is not None and pc.df is not None
        watches = [pa.global_df.watch(), pb.global_df.watch()]
        await pc.df.register(svc("cam@uav-c", "cam", V.PUBLIC))
        assert pa.df is not None
        await pa.df.register(svc("cam@uav-a", "cam", V.PUBLIC))
        for w in watches:
            await wait_for(w, lambda e: e.op == "register" and e.platform == "uav-c")
        assert sorted(s.provider for s in pb.global_df.services()) == ["cam@uav-a", "cam@uav-c"]
        # uav-c's connection goes at once, as when its process is killed: no deregister sent.
        await pc.transport.aclose()
        for w in watches:
            gone = await wait_for(w, lambda e: e.op == "platform-gone")
            assert gone == DirectoryEvent("platform-gone", "uav-c", None)
        for view in (pa.global_df, pb.global_df):
            assert [s.provider for s in view.services()] == ["cam@uav-a"]
            assert view.platforms == ["uav-a", "uav-b"]
        for w in watches:
            w.close()
    # ...and uav-c's platform still closed cleanly over its dead transport (checked on exit).


async def test_a_platform_coming_back_is_queried_again() -> None:
    hub = MemoryHub()
    async with asyncio.timeout(5), platforms("uav-a", hub=hub) as [pa]:
        assert pa.global_df is not None
        async with pa.global_df.watch() as w:
            for round_ in range(2):
                async with hub.transport() as t, AgentPlatform("uav-b", t, federation="t") as pb:
                    assert pb.df is not None
                    await pb.df.register(svc("cam@uav-b", f"cam{round_}", V.PUBLIC))
                    e = await wait_for(w, lambda e: e.op == "register")
                    assert e.service is not None and e.service.name == f"cam{round_}"
                await wait_for(w, lambda e: e.op == "platform-gone")
                assert pa.global_df.services() == []


async def test_the_view_s_version_changes_with_its_services() -> None:
    # what a cache of the view (the federation service's providers) relies on: equal
    # versions, equal services
    hub = MemoryHub()
    async with asyncio.timeout(5), platforms("uav-a", hub=hub) as [pa]:
        view = pa.global_df
        assert view is not None
        seen = [(view.version, view.services())]

        def changed() -> bool:
            before_version, before = seen[-1]
            seen.append((view.version, view.services()))
            return view.version != before_version and view.services() != before

        async with view.watch() as w:
            async with hub.transport() as t, AgentPlatform("uav-b", t, federation="t") as pb:
                assert pb.df is not None
                await wait_for(w, lambda e: e.op == "platform-up" and e.platform == "uav-b")
                assert view.version != seen[-1][0]  # its snapshot taken (no public service)
                seen.append((view.version, view.services()))
                await pb.df.register(svc("cam@uav-b", "cam", V.PUBLIC, resolution=720))
                await wait_for(w, lambda e: e.op == "register" and e.platform == "uav-b")
                assert changed()
                await pb.df.modify(svc("cam@uav-b", "cam", V.PUBLIC, resolution=1080))
                await wait_for(w, lambda e: e.op == "modify")
                assert changed()
                await pb.df.register(svc("cam@uav-b", "rear", V.PUBLIC))
                await wait_for(w, lambda e: e.op == "register" and e.service.name == "rear")
                assert changed()
                await pb.df.deregister("cam@uav-b", "cam")
                await wait_for(w, lambda e: e.op == "deregister")
                assert changed() and names(view.services()) == ["rear"]
            await wait_for(w, lambda e: e.op == "platform-gone")
            assert changed() and view.services() == []


async def test_bad_directory_events_are_counted_and_ignored() -> None:
    async with asyncio.timeout(5), platforms("uav-a", "uav-b") as [pa, pb]:
        view = pa.global_df
        assert view is not None and pb.df is not None
        key = pb.key("df-events")
        forged = {"v": 1, "op": "register", "service": svc("cam@uav-a", "forged").to_obj()}
        for payload in (
            b"junk",
            orjson.dumps({"v": 2, "op": "register", "service": svc("cam@uav-b", "x").to_obj()}),
            orjson.dumps({"v": 1, "op": "explode", "service": svc("cam@uav-b", "x").to_obj()}),
            orjson.dumps({"v": 1, "op": "register", "service": {"name": "x"}}),
            orjson.dumps(forged),  # uav-b speaking for an agent of uav-a
        ):
            await pb.transport.publish(key, payload)
        async with view.watch() as w:
            await pb.df.register(svc("cam@uav-b", "real", V.PUBLIC))
            e = await wait_for(w, lambda e: e.op == "register")
        assert e.service is not None and e.service.name == "real"
        assert view.invalid == 5
        assert [s.name for s in view.services()] == ["real"]


async def test_events_from_a_platform_not_alive_are_ignored() -> None:
    async with asyncio.timeout(5), platforms("uav-a", "uav-b") as [pa, pb]:
        view = pa.global_df
        assert view is not None and pb.df is not None
        ghost = {"v": 1, "op": "register", "service": svc("cam@ghost", "x").to_obj()}
        await pb.transport.publish(pa.key("df-events", "ghost"), orjson.dumps(ghost))
        async with view.watch() as w:
            await pb.df.register(svc("cam@uav-b", "real", V.PUBLIC))
            e = await wait_for(w, lambda e: e.op == "register")
        assert e.platform == "uav-b"
        assert [s.provider for s in view.services()] == ["cam@uav-b"]


def test_the_wire_document_lists_every_field_of_a_service_and_a_query() -> None:
    text = (Path(__file__).resolve().parent.parent / "docs" / "wire.md").read_text()
    section = text.split("\n## Directory service descriptions\n", 1)[1].split("\n## ", 1)[0]
    fields = re.findall(r"^\| `([a-z_]+)` \|", section, re.MULTILINE)
    assert fields == list(ServiceDescription.model_fields)
    query = section.split("A query has the optional fields", 1)[1].split("no other field", 1)[0]
    assert set(re.findall(r"`([a-z_]+)`", query)) == set(ServiceQuery.model_fields)
    visibility = re.search(r"^\| `visibility` \| (.*?) \|", section, re.MULTILINE)
    assert visibility is not None
    assert re.findall(r'`"([a-z]+)"`', visibility.group(1)) == [v.value for v in Visibility]


# Long enough that a start waiting out one directory query, as MQTT's query would, is far
# over the bound the test sets (half of it), on any machine.
MQTT_QUERY_TIMEOUT = 8.0


async def test_a_start_over_mqtt_does_not_wait_out_the_directory_query(
    mosquitto: tuple[str, int],
) -> None:
    """Over MQTT a start's snapshot ends once every trusted platform alive answered.

    A query there cannot know who heard it; the tokens alive say whom to expect. The view
    is whole when the start returns, and an untrusted token is not waited for.
    """
    host, port = mosquitto
    names = ["uav-a", "uav-b", "uav-c", "uav-d"]
    keys = {n: KeyPair.generate(n) for n in names}
    trust = {n: k.public_key for n, k in keys.items()}
    async with contextlib.AsyncExitStack() as stack:
        outsider = await stack.enter_async_context(MqttTransport(MqttConfig(host=host, port=port)))
        await outsider.declare_token("dyknow/t/v1/alive/mallory")  # in no trust file
        started: list[AgentPlatform] = []
        for n in names:
            transport = MqttTransport(MqttConfig(host=host, port=port, client_id=n))
            await stack.enter_async_context(transport)
            channel = InterfaceAgent(keys[n], TrustStore("t", trust))
            platform = AgentPlatform(
                n, transport, federation="t", channel=channel, query_timeout=MQTT_QUERY_TIMEOUT
            )
            t0 = asyncio.get_running_loop().time()
            await stack.enter_async_context(platform)
            took = asyncio.get_running_loop().time() - t0
            assert took < MQTT_QUERY_TIMEOUT / 2, f"{n} started in {took:.2f} s"
            view = platform.global_df
            assert view is not None and platform.df is not None
            assert view.platforms == [p.name for p in [*started, platform]]
            assert sorted(s.provider for s in view.services()) == [f"cam@{p.name}" for p in started]
            await platform.df.register(svc(f"cam@{n}", "cam", V.PUBLIC))
            started.append(platform)


async def test_platforms_closing_over_a_stalled_broker_do_not_wait_for_it_one_by_one(
    own_mosquitto: tuple[str, int, subprocess.Popen[bytes]],
) -> None:
    """Closing platforms whose MQTT broker stopped answering takes no broker timeout each.

    Their tokens are still cleared: once the broker runs again, none is left alive.
    """
    host, port, broker = own_mosquitto
    federation = f"stall-{secrets.token_hex(4)}"
    names = ["uav-a", "uav-b", "uav-c"]
    config = MqttConfig(host=host, port=port)
    loop = asyncio.get_running_loop()
    stack = contextlib.AsyncExitStack()
    try:
        async with stack:
            for n in names:
                transport = MqttTransport(config.model_copy(update={"client_id": n}))
                await stack.enter_async_context(transport)
                await stack.enter_async_context(AgentPlatform(n, transport, federation=federation))
            broker.send_signal(signal.SIGSTOP)
            t0 = loop.time()
        took = loop.time() - t0
    finally:
        broker.send_signal(signal.SIGCONT)
    # each one used to wait for the broker to acknowledge its token's clearing: the
    # connect timeout, one platform after another
    assert took < config.connect_timeout / 2, f"{len(names)} platforms closed in {took:.1f} s"
    async with MqttTransport(config) as watcher:
        key = f"dyknow/{federation}/v1/alive/*"
        deadline = loop.time() + config.connect_timeout
        alive = await watcher.tokens(key, timeout=5.0)
        while alive and loop.time() < deadline:  # each waits for a trip through the broker
            alive = await watcher.tokens(key, timeout=5.0)
        assert alive == [], f"still alive once the broker runs again: {alive}"


async def test_a_directory_whose_presence_watch_ended_still_takes_a_signed_leave(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # its presence watch ended by the transport (MQTT: refused after a reconnection), a
    # platform still learns of one that leaves cleanly, by its signed leave on the
    # directory's events: only one gone without it (a crash) stays listed, and the
    # loss's meaning says no more than that
    hub = MemoryHub()
    async with asyncio.timeout(10), platforms("uav-a", hub=hub) as [pa]:
        gdf = pa.global_df
        assert gdf is not None
        lost: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        pa.on_lost(lambda what, why: lost.done() or lost.set_result(what))
        async with gdf.watch() as w:
            async with hub.transport() as t, AgentPlatform("late", t, federation="t") as late:
                assert late.df is not None
                await late.df.register(svc("cam@late", "cam", V.PUBLIC))
                await wait_for(w, lambda e: e.op == "register" and e.platform == "late")
                _, presence = gdf._subs  # the events subscription first, the presence watch
                presence.inbox.close()  # as MQTT's `_end` does: the iterator ends, not closed
                assert await lost == f"directory presence watch {pa.key('alive', '*')}"
            gone = await wait_for(w, lambda e: e.op == "platform-gone")
        assert gone == DirectoryEvent("platform-gone", "late", None)
        assert gdf.platforms == ["uav-a"] and gdf.services() == []
    (said,) = [r.getMessage() for r in caplog.records if r.name == "agents._platform"]
    assert said.endswith(
        "other platforms coming and going are no longer seen but by their signed leaves "
        "and the directory's rechecks (where they run): till then one that goes without "
        "its signed leave (a crash) stays in this platform's directory, one that comes is "
        "not added to it"
    ), said
