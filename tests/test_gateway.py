"""The Gateway Agent: DyKnow over ACL between two platforms with authenticated channels."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import pytest

from agents import (
    LATER,
    MAX_MESSAGE_BYTES,
    ACLMessage,
    Agent,
    AgentPlatform,
    Failed,
    HandedOver,
    InterfaceAgent,
    KeyPair,
    MemoryHub,
    Performative,
    Refused,
    ReplyTimeout,
    ServiceDescription,
    SubscriptionEnded,
    TrustStore,
    query_if,
    query_ref,
    request,
    subscribe,
)
from dyknow_core import NS_PER_S, DyKnowError, DyKnowInstance, ManualClock, Source
from federation import GATEWAY_SERVICE_TYPE, GatewayAgent, GatewayRefusal, GatewayService
from federation._gateway import GatewayStats
from federation._gateway_service import answer_to_json

FED = "t"
T0 = 1000 * NS_PER_S  # the instance's now when a test starts
GW = "gateway@uav-a"


@dataclass
class World:
    """uav-a runs DyKnow and its gateway; operator asks it, through Interface Agents."""

    clock: ManualClock
    dk: DyKnowInstance
    uav: AgentPlatform
    operator: AgentPlatform
    gateway: GatewayAgent
    asker: Agent
    speed: Source
    state: Source

    async def ask(self, content: Any) -> Any:
        return await request(self.asker, GW, content, ontology="dyknow", timeout=5)


@contextlib.asynccontextmanager
async def world(**gateway_options: Any) -> AsyncIterator[World]:
    """Two platforms on one in-memory hub; on exit, checks that no task is left behind."""
    ka, ko = KeyPair.generate("uav-a"), KeyPair.generate("operator")
    keys = {"uav-a": ka.public_key, "operator": ko.public_key}
    hub = MemoryHub()
    clock = ManualClock(T0)
    async with contextlib.AsyncExitStack() as stack:
        dk = await stack.enter_async_context(DyKnowInstance("uav-a", clock=clock))
        speed = dk.add_source("car/car5/speed")
        state = dk.add_source("car5-state")
        ta = await stack.enter_async_context(hub.transport())
        to = await stack.enter_async_context(hub.transport())
        uav = await stack.enter_async_context(
            AgentPlatform(
                "uav-a", ta, federation=FED, channel=InterfaceAgent(ka, TrustStore(FED, keys))
            )
        )
        operator = await stack.enter_async_context(
            AgentPlatform(
                "operator", to, federation=FED, channel=InterfaceAgent(ko, TrustStore(FED, keys))
            )
        )
        gateway = await uav.add(GatewayAgent(dk, **gateway_options))
        asker = await operator.add(Agent("asker"))
        yield World(clock, dk, uav, operator, gateway, asker, speed, state)
    assert asyncio.all_tasks() == {asyncio.current_task()}


def push_trajectory(w: World, n: int = 30, every: float = 10.0) -> None:
    """car5's state every ``every`` s, valid from 300 s ago up to now; positions as tuples."""
    for i in range(n):
        tv = T0 - 300 * NS_PER_S + round(i * every * NS_PER_S)
        w.state.push({"pos": (float(i), 2.0 * i), "speed": 10.0 + i}, valid_time=tv)


async def eventually(check: Callable[[], bool], timeout: float = 2.0) -> None:
    """Wait (bounded) until ``check()`` holds."""
    # What is checked is changed by the gateway's own tasks, which offer nothing to await.
    async with asyncio.timeout(timeout):
        while not check():  # noqa: ASYNC110
            await asyncio.sleep(0.005)


async def refusal(call: Awaitable[Any]) -> str:
    """The reason a refused call carries."""
    with pytest.raises(Refused) as info:
        await call
    assert info.value.message is not None
    reason = info.value.message.content
    assert isinstance(reason, str)
    return reason


# -- FIPA-Request and FIPA-Query ----------------------------------------------------------


async def test_list_labels_by_request_and_query_ref() -> None:
    async with world() as w:
        assert await w.ask({"action": "list-labels"}) == {
            "labels": ["car/car5/speed", "car5-state"]
        }
        assert await w.ask({"action": "list-labels", "pattern": "car/*"}) == {
            "labels": ["car/car5/speed"]
        }
        found = await query_ref(
            w.asker, GW, {"action": "list-labels", "pattern": "car5*"}, ontology="dyknow"
        )
        assert found == {"labels": ["car5-state"]}
        # it went through uav-a's Interface Agent, authenticated
        audit = w.uav.channel
        assert isinstance(audit, InterfaceAgent)
        assert audit.audit.counts["accepted"] >= 3
        assert audit.audit.counts["dropped"] == 0


async def test_query_latest_at_between() -> None:
    async with world() as w:
        for i in range(5):
            w.speed.push(float(i), valid_time=T0 + i * NS_PER_S)
        w.clock.advance_seconds(10)
        latest = await w.ask({"action": "query", "label": "car/car5/speed"})
        assert latest["label"] == "car/car5/speed"
        assert latest["query_time"] == 1010.0
        assert [row[:2] for row in latest["samples"]] == [[4.0, 1004.0]]

        at = await query_ref(
            w.asker,
            GW,
            {"label": "car/car5/speed", "kind": "at", "t": 1002.5, "approximation": "linear"},
            ontology="dyknow",
        )
        assert at["samples"][0][:2] == [2.5, 1002.5]

        between = await w.ask(
            {
                "action": "query",
                "label": "car/car5/speed",
                "kind": "between",
                "from": 1001,
                "to": 1003,
            }
        )
        assert [row[:2] for row in between["samples"]] == [
            [1.0, 1001.0],
            [2.0, 1002.0],
            [3.0, 1003.0],
        ]
        # available times are seconds on the instance's time line too
        assert all(1000.0 <= row[2] < 1000.001 for row in between["samples"])

        # "as believed at": the samples were available at 1000 s; before that, nothing
        before = await w.ask(
            {"action": "query", "label": "car/car5/speed", "kind": "between", "as_of": 999}
        )
        assert before["samples"] == []


async def test_relative_trajectory_query() -> None:
    async with world() as w:
        push_trajectory(w)  # 30 states, valid from now - 300 s to now - 10 s
        answer = await w.ask(
            {
                "action": "query",
                "label": "car5-state",
                "kind": "between",
                "from": -120,
                "relative": True,
            }
        )
        rows = answer["samples"]
        # the last two minutes: valid times now - 120 … now - 10, every 10 s
        assert [row[1] for row in rows] == [1000.0 - 120 + 10 * k for k in range(12)]
        # tuples (positions) travel as JSON arrays
        assert rows[0][0] == {"pos": [18.0, 36.0], "speed": 28.0}
        assert rows[-1][0]["pos"] == [29.0, 58.0]

        # relative times follow the provider's clock, not the asker's
        w.clock.advance_seconds(60)
        later = await w.ask(
            {
                "action": "query",
                "label": "car5-state",
                "kind": "between",
                "from": -120,
                "relative": True,
            }
        )
        assert len(later["samples"]) == 6


async def test_create_stream_with_a_policy() -> None:
    async with world() as w:
        created = await w.ask(
            {
                "action": "create-stream",
                "label": "car/car5/speed",
                "output": "car/car5/speed-1hz",
                "policy": {"sample_period": 1.0, "lower": 0, "upper": 50},
            }
        )
        assert created == {"label": "car/car5/speed-1hz", "source": "car/car5/speed"}
        assert "car/car5/speed-1hz" in (await w.ask({"action": "list-labels"}))["labels"]
        for i in range(41):  # every 0.1 s for 4 s; one value out of bounds
            w.speed.push(99.0 if i == 20 else float(i), valid_time=T0 + i * NS_PER_S // 10)
        w.clock.advance_seconds(5)
        answer = await w.ask(
            {"action": "query", "label": "car/car5/speed-1hz", "kind": "between", "from": 0}
        )
        # one sample per second on the grid; the out-of-bounds one at 1002 s is filtered,
        # so that grid point takes the last sample of its period
        assert [row[:2] for row in answer["samples"]] == [
            [0.0, 1000.0],
            [10.0, 1001.0],
            [19.0, 1002.0],
            [30.0, 1003.0],
            [40.0, 1004.0],
        ]
        assert w.gateway.service.created == {"car/car5/speed-1hz": "gateway:car/car5/speed-1hz"}


# -- refusals ------------------------------------------------------------------------------


async def test_refusals_carry_the_reason() -> None:
    async with world() as w:
        reason = await refusal(w.ask({"action": "query", "label": "car/car9/speed"}))
        assert reason.startswith("unknown label 'car/car9/speed'")
        assert "car/car5/speed" in reason  # the known labels are named

        reason = await refusal(w.ask({"action": "fly", "to": "home"}))
        assert (
            reason
            == "unknown action 'fly' (known: create-stream, list-labels, query, remove-stream)"
        )

        reason = await refusal(w.ask("list-labels"))
        assert reason == "content must be a JSON object with an 'action'"

        bad_policy = {
            "action": "create-stream",
            "label": "car/car5/speed",
            "output": "x",
            "policy": {"sample_period": -1},
        }
        reason = await refusal(w.ask(bad_policy))
        assert "sample_period" in reason and "0.001" in reason  # the edge's minimum
        assert not w.dk.has_label("x")

        reason = await refusal(w.ask({**bad_policy, "policy": {"sample_period": 1, "every": 2}}))
        assert reason == "field 'policy.every': Extra inputs are not permitted"

        reason = await refusal(
            w.ask({"action": "create-stream", "label": "car/car9/speed", "output": "y"})
        )
        assert reason.startswith("unknown label 'car/car9/speed'")

        reason = await refusal(
            w.ask({"action": "create-stream", "label": "car/car5/speed", "output": "car5-state"})
        )
        assert reason == "label 'car5-state' is already published"

        reason = await refusal(w.ask({"action": "query", "label": "car5-state", "kind": "at"}))
        assert reason == "a query 'at' needs 't'"

        reason = await refusal(
            w.ask({"action": "query", "label": "car5-state", "kind": "between", "from": 1e300})
        )
        assert reason.startswith("field 'from'")

        reason = await refusal(
            query_ref(
                w.asker,
                GW,
                {"action": "create-stream", "label": "car/car5/speed", "output": "z"},
                ontology="dyknow",
            )
        )
        assert "FIPA-Request" in reason
        reason = await refusal(query_if(w.asker, GW, {"label": "car5-state"}, ontology="dyknow"))
        assert "query-ref" in reason


async def test_subscribe_refusals_carry_the_reason() -> None:
    async with world() as w:
        reason = await refusal(
            subscribe(w.asker, GW, {"label": "car/car9/speed"}, ontology="dyknow")
        )
        assert reason.startswith("unknown label 'car/car9/speed'")

        reason = await refusal(
            subscribe(
                w.asker,
                GW,
                {"label": "car/car5/speed", "policy": {"sample_period": 0}},
                ontology="dyknow",
            )
        )
        assert "sample_period" in reason and "0.001" in reason  # the edge's minimum

        reason = await refusal(
            subscribe(
                w.asker,
                GW,
                {"label": "car/car5/speed", "policy": {"change": "sometimes"}},
                ontology="dyknow",
            )
        )
        assert reason.startswith("policy field 'change")

        reason = await refusal(subscribe(w.asker, GW, ["car/car5/speed"], ontology="dyknow"))
        assert reason.startswith("field 'content'")
        assert w.gateway.subscriptions == {}


# -- FIPA-Subscribe ------------------------------------------------------------------------


async def test_subscribe_informs_follow_the_policy_and_cancel_stops_them() -> None:
    async with world() as w:
        stream = await subscribe(
            w.asker,
            GW,
            {"label": "car/car5/speed", "policy": {"sample_period": 0.5}},
            ontology="dyknow",
        )
        assert stream.agree.performative == "agree"
        assert w.gateway.subscriptions == {
            ("asker@operator", stream.message.conversation_id): "car/car5/speed"
        }

        for i in range(21):  # every 0.1 s for 2 s
            w.speed.push(float(i), valid_time=T0 + i * NS_PER_S // 10)
        rows: list[list[Any]] = []
        while len(rows) < 5:
            content = await stream.get(timeout=5)
            assert content["label"] == "car/car5/speed"
            rows.extend(content["samples"])
        # one sample per 0.5 s of valid time, on the grid
        assert [row[:2] for row in rows] == [
            [0.0, 1000.0],
            [5.0, 1000.5],
            [10.0, 1001.0],
            [15.0, 1001.5],
            [20.0, 1002.0],
        ]

        await stream.cancel()
        assert stream.ended
        assert w.gateway.subscriptions == {}
        assert w.dk.stream("car/car5/speed").subscriptions == []  # the core one is closed
        informs = w.gateway.gateway_stats.informs
        received = w.asker.stats.received

        for i in range(21, 41):
            w.speed.push(float(i), valid_time=T0 + i * NS_PER_S // 10)
        # a round trip through the gateway: an inform sent meanwhile would arrive first
        await w.ask({"action": "query", "label": "car/car5/speed"})
        assert w.gateway.gateway_stats.informs == informs
        assert w.asker.stats.received == received + 1  # the query's answer only
        assert w.asker.stats.late == 0
        with pytest.raises(SubscriptionEnded):
            await stream.get(timeout=1)


async def test_subscribe_replays_history_and_splits_large_batches() -> None:
    async with world() as w:
        n = 3000
        blob = "x" * 200  # 3000 x ~250 bytes: more than one message may carry
        for i in range(n):
            w.state.push({"i": i, "blob": blob}, valid_time=T0 - (n - i) * NS_PER_S // 100)
        stream = await subscribe(
            w.asker,
            GW,
            {"label": "car5-state", "policy": {"from": -60, "relative": True}},
            ontology="dyknow",
        )
        seen: list[int] = []
        informs = 0
        while len(seen) < n:
            content = await stream.get(timeout=5)
            informs += 1
            assert stream.last is not None
            assert len(stream.last.to_json()) <= MAX_MESSAGE_BYTES
            seen.extend(row[0]["i"] for row in content["samples"])
        assert seen == list(range(n))
        assert informs >= 3
        assert w.gateway.gateway_stats.too_large == 0
        await stream.cancel()


async def test_subscription_ends_cleanly_when_the_stream_ends() -> None:
    async with world() as w:
        stream = await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        w.speed.push(1.0)
        assert (await stream.get(timeout=5))["samples"][0][0] == 1.0
        w.dk.remove_process("source:car/car5/speed")
        with pytest.raises(SubscriptionEnded):
            await stream.get(timeout=5)
        assert stream.ended
        assert w.gateway.subscriptions == {}


async def test_subscription_ends_at_the_policy_end() -> None:
    async with world() as w:
        stream = await subscribe(
            w.asker,
            GW,
            {"label": "car/car5/speed", "policy": {"to": 1001}},
            ontology="dyknow",
        )
        for i in range(4):
            w.speed.push(float(i), valid_time=T0 + i * NS_PER_S // 2)
        got = [row[0] async for content in stream for row in content["samples"]]
        assert got == [0.0, 1.0, 2.0]
        assert w.gateway.subscriptions == {}


async def test_gateway_stopping_fails_its_subscriptions() -> None:
    async with world() as w:
        stream = await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        await w.gateway.stop()
        with pytest.raises(Failed, match="gateway@uav-a stopped"):
            await stream.get(timeout=5)
        assert w.dk.stream("car/car5/speed").subscriptions == []


async def test_subscriptions_of_a_platform_that_leaves_are_dropped() -> None:
    async with world() as w:
        await _create(w.asker, "car5-state", "op/t")
        await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        await subscribe(w.asker, GW, {"label": "car5-state"}, ontology="dyknow")
        assert len(w.gateway.subscriptions) == 2
        await w.operator.__aexit__(None, None, None)
        await eventually(lambda: w.gateway.subscriptions == {})
        assert w.dk.stream("car/car5/speed").subscriptions == []
        # the stream it created stays (it may come back; `max_streams` bounds them) and
        # counts in its share of them; its subscriptions count no more in theirs
        assert w.gateway.service.created == {"op/t": "gateway:op/t"}
        assert (w.gateway.service.held_by("operator"), w.gateway.held_by("operator")) == (1, 0)
        assert w.dk.has_label("op/t") and w.gateway.gateway_stats.streams_removed == 0


async def test_a_platform_revoked_from_another_thread_loses_what_it_holds_here() -> None:
    async with world() as w:
        local = await w.uav.add(Agent("local"))
        await _create(w.asker, "car/car5/speed", "op/t")
        await _create(local, "car/car5/speed", "mine/t")
        await subscribe(w.asker, GW, {"label": "car5-state"}, ontology="dyknow")
        interface = w.uav.channel
        assert isinstance(interface, InterfaceAgent)
        # a program's thread revokes: done in the gateway's own loop
        assert await asyncio.to_thread(interface.trust.remove, "operator")
        await eventually(lambda: w.gateway.gateway_stats.streams_removed == 1)
        assert w.gateway.subscriptions == {}
        assert not w.dk.has_label("op/t") and w.dk.has_label("mine/t")
        assert w.gateway.service.created == {"mine/t": "gateway:mine/t"}
        records = [r for r in interface.audit.records if r.get("stage") == "trust"]
        assert [(r["verdict"], r["code"], r.get("stream")) for r in records] == [
            ("revoked", "untrusted", None),  # its sessions forgotten, at once
            ("ended", "untrusted", "car5-state"),
            ("ended", "untrusted", "op/t"),
        ], records


async def test_informs_to_an_agent_that_left_end_its_subscription() -> None:
    async with world() as w:
        await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        await w.asker.stop()
        w.speed.push(1.0)  # the inform bounces: no such agent on operator
        await eventually(lambda: w.gateway.subscriptions == {})


async def test_a_subscribers_bounce_reason_is_logged_as_one_capped_line(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A subscriber's failure is its word: the gateway drops the subscription and logs the
    reason on one line, its newline escaped (no forged log line), cut to `QUOTE_MAX`
    characters with how long it was, however long (10 kB) the subscriber made it."""
    from federation._quote import QUOTE_MAX

    async with world() as w:
        stream = await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        forged = "stopped\nERROR federation._gateway: gateway@uav-a: all subscriptions leaked"
        why = forged + "x" * 10_000
        bounce = w.asker.message(
            Performative.FAILURE,
            GW,
            why,
            ontology="dyknow",
            conversation_id=stream.message.conversation_id,
        )
        with caplog.at_level("INFO", logger="federation._gateway"):
            await w.asker.send(bounce)
            await eventually(lambda: w.gateway.subscriptions == {})
        said = [r.getMessage() for r in caplog.records if " dropped: " in r.getMessage()]
        assert said == [
            f"{w.gateway}: subscription of asker@operator to 'car/car5/speed' dropped: "
            f"stopped\\x0a{why[8 : QUOTE_MAX - 3]}… ({len(why)} characters, "
            f"{len(why) - QUOTE_MAX + 3} left out)"
        ]


# -- the directory -------------------------------------------------------------------------


async def test_registers_a_protected_service_by_default() -> None:
    async with world() as w:
        assert w.uav.df is not None
        [service] = w.uav.df.search(type=GATEWAY_SERVICE_TYPE)
        assert service == ServiceDescription(
            name="dyknow",
            type="dyknow-gateway",
            provider=GW,
            ontology="dyknow",
            protocols=["fipa-request", "fipa-query", "fipa-subscribe"],
            properties={"instance": "uav-a"},
            visibility="protected",
        )
        assert w.operator.global_df is not None
        assert w.operator.global_df.search(type=GATEWAY_SERVICE_TYPE) == []
        await w.gateway.stop()
        assert w.uav.df.search(type=GATEWAY_SERVICE_TYPE) == []


async def test_public_gateway_is_in_the_global_directory() -> None:
    async with world(visibility="public", service_name="uav-a-dyknow") as w:
        gdf = w.operator.global_df
        assert gdf is not None
        await eventually(lambda: len(gdf.search(type=GATEWAY_SERVICE_TYPE)) == 1)
        [service] = gdf.search(type=GATEWAY_SERVICE_TYPE)
        assert (service.name, service.provider) == ("uav-a-dyknow", GW)


async def test_without_a_service_other_platforms_are_denied() -> None:
    async with world(register=False) as w:
        reason = await refusal(w.ask({"action": "list-labels"}))
        assert reason.startswith("access denied")
        # its own platform still may
        local = await w.uav.add(Agent("local"))
        assert await request(local, GW, {"action": "list-labels"}, ontology="dyknow", timeout=5)


def test_the_quick_query_answers_and_refuses_as_the_models_do() -> None:
    clock = ManualClock(T0)
    dk = DyKnowInstance("uav-a", clock=clock)
    src = dk.add_source("a/b")
    for v in (1, 2.5, (3, 4)):
        src.push(v)
    dk.add_source("empty")
    service = GatewayService(dk)

    def by_the_models(content: Any) -> Any:
        try:
            return answer_to_json(service.query(service.parse(content)))  # type: ignore[arg-type]
        except GatewayRefusal as exc:
            return ("refused", exc.reason)
        except DyKnowError as exc:
            return ("refused", str(exc))

    def performed(content: Any) -> Any:
        try:
            return service.perform(content)
        except GatewayRefusal as exc:
            return ("refused", exc.reason)

    for content in (
        {"action": "query", "label": "a/b"},
        {"action": "query", "label": "a/b", "kind": "latest"},
        {"action": "query", "label": "empty"},
        {"action": "query", "label": "nope"},
        {"action": "query", "label": 3},
        {"action": "query"},
        {"action": "query", "label": "a/b", "kind": "LATEST"},
        {"action": "query", "label": "a/b", "kind": None},
        {"action": "query", "label": "a/b", "extra": 1},
        {"action": "query", "label": "a/b", "kind": "at"},
    ):
        assert performed(content) == by_the_models(content), content


_AT_ONCE_CONTENTS: list[Any] = [
    {"action": "query", "label": "car/car5/speed"},
    {"action": "query", "label": "car/car5/speed", "kind": "latest"},
    {"label": "car/car5/speed"},  # query-ref's default action; a request refuses it
    {"action": "query", "label": "car5-state"},  # no sample yet: none in the answer
    {"action": "query", "label": "car/car9/speed"},  # no such label
    {"action": "query", "label": "import/uav-b/x"},  # reserved
    {"action": "query", "label": "car/car5/speed", "kind": "at", "t": 1001},
    {"action": "query", "label": "car/car5/speed", "extra": 1},
    {"action": "list-labels"},
    ["query", "car/car5/speed"],
]


async def test_a_query_for_the_latest_is_answered_at_once_as_the_handlers_answer() -> None:
    """Another platform's plain latest query is answered as it comes (no mailbox, no task),
    with the handlers' very answer; what they refuse they still refuse, count and audit."""

    async def outcomes(at_once: bool) -> tuple[list[Any], int, GatewayStats, list[Any]]:
        async with world() as w:
            w.gateway._at_once = at_once
            for i in range(3):
                w.speed.push(float(i), valid_time=T0 + i * NS_PER_S)
            got: list[Any] = []
            for content in _AT_ONCE_CONTENTS:
                for ask in (request, query_ref):
                    try:
                        got.append(("inform", await ask(w.asker, GW, content, ontology="dyknow")))
                    except Refused as exc:
                        assert exc.message is not None
                        got.append(("refuse", exc.message.content))
            channel = w.uav.channel
            assert isinstance(channel, InterfaceAgent)
            audited = [
                (r["verdict"], r.get("stage"), r.get("code"), r["performative"])
                for r in channel.audit.records
            ]
            stats = w.gateway.stats
            assert stats.handled == 2 * len(_AT_ONCE_CONTENTS)
            return got, stats.answered_at_once, w.gateway.gateway_stats, audited

    quick = await outcomes(True)
    # the first two and the label without a sample by both asks, query-ref's default action
    assert quick == (quick[0], 7, quick[2], quick[3])
    assert quick[0][0] == quick[0][1]  # by request and by query-ref
    assert quick[0][0][1]["samples"][0][:2] == [2.0, 1002.0]
    assert quick[2].reserved_refused == 2
    assert await outcomes(False) == (quick[0], 0, quick[2], quick[3])


async def test_an_answer_on_zenohs_thread_is_handed_over_only_when_plain() -> None:
    """The answer made on zenoh's thread goes to its reply without a copy when it is plain
    JSON made afresh for that reply, and is copied (a plain dict) otherwise; either way the
    reply's bytes are those of the answer the loop's handler gives."""
    async with world() as w:
        # a stream's first ask on the thread is the loop's (`Cache.latest_now`): watched since
        for label in ("car/car5/speed", "car5-state"):
            assert w.dk.latest_now(label) is None
        w.speed.push(12.5, valid_time=T0)
        w.state.push({"pos": (1.0, 2.0)}, valid_time=T0)  # a tuple: not plain JSON
        for label, plain in (("car/car5/speed", True), ("car5-state", False)):
            message = ACLMessage.build(
                performative=Performative.REQUEST,
                sender="asker@operator",
                receivers=[GW],
                content={"action": "query", "label": label},
                ontology="dyknow",
                protocol="fipa-request",
                conversation_id=f"c-{label}",
                reply_with="r1",
            )
            first = w.gateway.answer_on_thread(message)
            second = w.gateway.answer_on_thread(message)
            assert (type(first) is HandedOver) is plain, label
            if plain:
                # nothing of one answer is in another: each is its reply's alone
                assert first.value is not second.value
                assert first.value["samples"] is not second.value["samples"]
                assert first.value["samples"][0] is not second.value["samples"][0]
            answer = first.value if plain else first
            assert answer == w.gateway.answer_at_once(message)
            by_loop = message.reply(
                Performative.INFORM, w.gateway.answer_at_once(message), sender=GW
            )
            by_lane = message.reply(Performative.INFORM, first, sender=GW)
            assert by_lane.to_json() == by_loop.to_json()


async def test_a_created_stream_needs_a_valid_output_label() -> None:
    async with world() as w:
        for output in ("", "x" * 100_000, "car 5", "car/#"):
            create = {"action": "create-stream", "label": "car/car5/speed", "output": output}
            reason = await refusal(w.ask(create))
            assert reason.startswith("output: semantic label ")
            assert "must be 1-256 characters, '/'-separated non-empty chunks" in reason
            assert len(reason) < 300 and not w.dk.has_label(output)
        assert w.gateway.gateway_stats.bad_label_refused == 4
        channel = w.uav.channel
        assert isinstance(channel, InterfaceAgent)
        recs = [r for r in channel.audit.records if r.get("stage") == "gateway"]
        assert [r["code"] for r in recs] == ["bad-label"] * 4
        assert recs[0]["sender"] == "asker@operator" and recs[0]["reason"].startswith("bad-label")


async def test_a_label_not_here_or_a_limit_is_refused_counted_and_audited() -> None:
    """Another platform asking a label not here (each way it may name one) is refused,
    counted and audited with the reason it is told; a limit is, whoever meets it; this
    platform's own agent asking a label not here is refused alike, unaudited."""
    async with world(max_streams=1, max_subscriptions=1) as w:
        w.dk.add_source("import/uav-c/secret")  # reserved: never named to another platform
        told = [
            await refusal(w.ask({"action": "query", "label": "car/car9/speed"})),
            await refusal(
                query_ref(w.asker, GW, {"label": "car/car9/speed"}, ontology="dyknow", timeout=5)
            ),
            await refusal(
                w.ask({"action": "query", "label": "car/car9/speed", "kind": "at", "t": 1})
            ),
            await refusal(
                w.ask({"action": "create-stream", "label": "car/car9/speed", "output": "op/x"})
            ),
            await refusal(
                subscribe(w.asker, GW, {"label": "car/car9/speed"}, ontology="dyknow", timeout=5)
            ),
        ]
        unknown = "unknown label 'car/car9/speed' (known labels: car/car5/speed, car5-state)"
        assert told == [unknown] * 5
        local = await w.uav.add(Agent("local"))
        mine = await refusal(
            request(local, GW, {"action": "query", "label": "car/car9/speed"}, ontology="dyknow")
        )
        assert mine.startswith("unknown label 'car/car9/speed'") and "import/uav-c" in mine
        # the limits: one created stream, one subscription
        await _create(w.asker, "car/car5/speed", "op/t")
        limits = [
            await refusal(
                w.ask({"action": "create-stream", "label": "car/car5/speed", "output": "op/u"})
            ),
        ]
        feed = await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        limits.append(
            await refusal(
                subscribe(local, GW, {"label": "car5-state"}, ontology="dyknow", timeout=5)
            )
        )
        assert limits == ["too many created streams (limit 1)", "too many subscriptions (limit 1)"]
        stats = w.gateway.gateway_stats
        assert (stats.unknown_label_refused, stats.limit_refused) == (5, 2)
        assert (stats.reserved_refused, stats.bad_label_refused, stats.access_refused) == (0, 0, 0)
        channel = w.uav.channel
        assert isinstance(channel, InterfaceAgent)
        recs = [r for r in channel.audit.records if r.get("stage") == "gateway"]
        assert [(r["code"], r["sender"], r["reason"]) for r in recs] == [
            ("unknown-label", "asker@operator", f"unknown-label: {unknown}")
        ] * 5 + [
            ("stream-limit", "asker@operator", f"stream-limit: {limits[0]}"),
            ("subscription-limit", "local@uav-a", f"subscription-limit: {limits[1]}"),
        ]
        assert [r["performative"] for r in recs[:5]] == [
            "request",
            "query-ref",
            "request",
            "request",
            "subscribe",
        ]
        assert all(r["verdict"] == "refused" and r["receivers"] == [GW] for r in recs)
        await feed.cancel()


async def test_a_refusal_audited_names_a_long_label_by_its_start_only() -> None:
    """Another platform naming a label of a whole message's size (not here, or reserved)
    is refused and audited with that label cut to its first 64 characters: each refusal's
    record is kept in memory (`AuditLog.records`) and written, a flood of whole labels
    would cost what the flooder sent, per request, there and on disk."""
    async with world() as w:
        long = "x" * 60_000
        unknown = await refusal(w.ask({"action": "query", "label": long}))
        reserved = await refusal(
            subscribe(w.asker, GW, {"label": "import/" + long}, ontology="dyknow", timeout=5)
        )
        assert unknown == (
            f"unknown label {'x' * 64 + '…'!r} (known labels: car/car5/speed, car5-state)"
        )
        assert reserved.startswith(f"label {'import/' + 'x' * 57 + '…'!r} is reserved")
        stats = w.gateway.gateway_stats
        assert (stats.unknown_label_refused, stats.reserved_refused) == (1, 1)
        channel = w.uav.channel
        assert isinstance(channel, InterfaceAgent)
        recs = [r for r in channel.audit.records if r.get("stage") == "gateway"]
        assert [(r["code"], r["reason"]) for r in recs] == [
            ("unknown-label", f"unknown-label: {unknown}"),
            ("reserved-label", f"reserved-label: {reserved}"),
        ]
        # a label as long as a semantic label may be is named whole
        whole = "y/" * 127 + "yy"
        assert len(whole) == 256
        told = await refusal(w.ask({"action": "query", "label": whole}))
        assert told.startswith(f"unknown label {whole!r} (known labels")


# -- made private while it runs (a sharing reload) ------------------------------------------


@contextlib.contextmanager
def held(agent: Agent, performative: str) -> Any:
    """Hold ``agent``'s incoming messages of ``performative`` out of its mailbox: the
    Interface Agent has let them in; yields (the messages held, an event set at the first,
    the function that hands them over)."""
    messages: list[Any] = []
    arrived = asyncio.Event()
    deliver, deliver_batch = agent._deliver, agent._deliver_batch

    def hold(message: Any) -> bool:
        if message.performative == performative:
            messages.append(message)
            arrived.set()
            return True
        return deliver(message)

    def hold_batch(batch: list[Any]) -> int:
        return sum(hold(m) for m in batch)

    def release() -> None:
        for message in messages:
            assert deliver(message)

    agent._deliver = hold  # type: ignore[method-assign]
    agent._deliver_batch = hold_batch  # type: ignore[method-assign]
    # nothing answered as it comes (`answer_at_once`): every message goes the mailbox's way
    agent.answer_at_once = None  # type: ignore[method-assign]
    try:
        yield messages, arrived, release
    finally:
        agent._deliver, agent._deliver_batch = deliver, deliver_batch  # type: ignore[method-assign]
        del agent.answer_at_once


@pytest.mark.parametrize("asking", ["subscribe", "request"])
async def test_what_waited_in_the_mailbox_while_the_gateway_went_private_is_refused(
    asking: str,
) -> None:
    async with world() as w:
        assert w.gateway.visibility == "protected"  # other platforms let in
        performative = "subscribe" if asking == "subscribe" else "request"
        with held(w.gateway, performative) as (messages, arrived, release):
            if asking == "subscribe":
                call: Awaitable[Any] = subscribe(
                    w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow"
                )
            else:
                call = w.ask({"action": "query", "label": "car/car5/speed"})
            asked = asyncio.ensure_future(call)
            async with asyncio.timeout(5):
                await arrived.wait()  # past the Interface Agent, not yet handled
            ended = await w.gateway.set_visibility("private", "closed by the operator")
            assert ended == ([], [], [])
            release()
            reason = await refusal(asked)
        assert reason == (
            f"access denied: {GW} offers no service that platform 'operator' may use"
        ), reason
        assert len(messages) == 1
        # nothing served: no subscription, no core subscription, no inform, ever
        for i in range(5):
            w.speed.push(float(i), valid_time=T0 + i * NS_PER_S)
        assert w.gateway.subscriptions == {}
        assert w.dk.stream("car/car5/speed").subscriptions == []
        received = w.asker.stats.received
        await refusal(w.ask({"action": "list-labels"}))  # a round trip: the Interface Agent's
        assert w.asker.stats.received == received + 1
        assert w.gateway.gateway_stats.informs == 0 == w.gateway.gateway_stats.subscriptions
        assert w.gateway.gateway_stats.access_refused == 1
        channel = w.uav.channel
        assert isinstance(channel, InterfaceAgent)
        (record,) = [r for r in channel.audit.records if r.get("stage") == "gateway"]
        assert record["code"] == "access-denied" and record["verdict"] == "refused"
        assert record["sender"] == "asker@operator" and record["from"] == "operator"
        assert record["performative"] == performative
        assert record["reason"] == f"access-denied: {reason}"
        # both counted as the platform's denials: the gateway's, then the Interface Agent's
        assert w.uav.stats.denied == 2


@pytest.mark.parametrize("asking", ["subscribe", "create-stream"])
async def test_what_waited_in_the_mailbox_while_its_platform_was_revoked_is_refused(
    asking: str,
) -> None:
    async with world() as w:
        interface = w.uav.channel
        assert isinstance(interface, InterfaceAgent)
        performative = "subscribe" if asking == "subscribe" else "request"
        with held(w.gateway, performative) as (messages, arrived, release):
            if asking == "subscribe":
                call: Awaitable[Any] = subscribe(
                    w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow", timeout=2
                )
            else:
                content = {"action": "create-stream", "label": "car/car5/speed", "output": "op/t"}
                call = request(w.asker, GW, content, ontology="dyknow", timeout=2)
            asked = asyncio.ensure_future(call)
            async with asyncio.timeout(5):
                await arrived.wait()  # past the Interface Agent, not yet handled
            assert interface.trust.remove("operator")
            release()
            with pytest.raises(ReplyTimeout):  # refused, and the refusal not sent: nothing is
                await asked
        reason = "platform 'operator' is not in the trust file (revoked)"
        assert interface.unsent_revoked == 1
        assert len(messages) == 1
        # nothing made for it: no subscription, no stream
        assert w.gateway.subscriptions == {}
        assert w.dk.stream("car/car5/speed").subscriptions == []
        assert w.gateway.service.created == {} and not w.dk.has_label("op/t")
        assert w.gateway.gateway_stats.access_refused == 1
        assert w.uav.stats.denied == 1
        (record,) = [r for r in interface.audit.records if r.get("stage") == "gateway"]
        assert record["code"] == "untrusted" and record["verdict"] == "refused"
        assert record["sender"] == "asker@operator" and record["from"] == "operator"
        assert record["performative"] == performative
        assert record["reason"] == f"untrusted: {reason}"


async def test_a_private_gateway_keeps_its_own_platforms_subscriptions() -> None:
    async with world() as w:
        local = await w.uav.add(Agent("local"))
        mine = await subscribe(local, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        theirs = await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        ended = await w.gateway.set_visibility("private", "closed by the operator")
        assert ended.subscriptions == [("asker@operator", "car/car5/speed")]
        with pytest.raises(Failed, match="closed by the operator"):
            await theirs.get(timeout=5)
        w.speed.push(1.0, valid_time=T0)
        first = await mine.get(timeout=5)  # served on
        assert [row[:2] for row in first["samples"]] == [[1.0, 1000.0]]
        again = await subscribe(local, GW, {"label": "car5-state"}, ontology="dyknow")
        assert again.agree.performative == "agree"  # and a new one agreed
        assert len(w.gateway.subscriptions) == 2
        assert w.gateway.gateway_stats.access_refused == 0
        await mine.cancel()
        await again.cancel()


async def test_going_private_removes_the_streams_other_platforms_created_and_keeps_its_own() -> (
    None
):
    async with world() as w:
        local = await w.uav.add(Agent("local"))

        async def create(asker: Agent, output: str) -> Any:
            content = {"action": "create-stream", "label": "car/car5/speed", "output": output}
            return await request(asker, GW, content, ontology="dyknow", timeout=5)

        await create(w.asker, "theirs/speed")
        await create(local, "mine/speed")
        # the stream another platform created, followed by it and by this platform
        theirs = await subscribe(w.asker, GW, {"label": "theirs/speed"}, ontology="dyknow")
        here = await subscribe(local, GW, {"label": "theirs/speed"}, ontology="dyknow")
        ended = await w.gateway.set_visibility("private", "closed by the operator")
        assert ended.subscriptions == [("asker@operator", "theirs/speed")]
        assert ended.streams == [("asker@operator", "theirs/speed")]
        assert w.gateway.gateway_stats.streams_removed == 1
        # gone as a removed process: no process, no label; this platform's subscriber told
        assert "gateway:theirs/speed" not in w.dk.processes
        assert not w.dk.has_label("theirs/speed")
        with pytest.raises(SubscriptionEnded):  # the responder's cancel: a clean end
            await here.get(timeout=5)
        with pytest.raises(Failed, match="closed by the operator"):
            await theirs.get(timeout=5)
        # this platform's own stream is kept, and serves on
        assert w.gateway.service.created == {"mine/speed": "gateway:mine/speed"}
        w.speed.push(7.0, valid_time=T0)
        answer = await request(
            local, GW, {"action": "query", "label": "mine/speed"}, ontology="dyknow", timeout=5
        )
        assert [row[:2] for row in answer["samples"]] == [[7.0, 1000.0]]
        # the removed one's slot is free: its output may be created again (here)
        await create(local, "theirs/speed")
        again = await w.gateway.set_visibility("private", "closed by the operator")
        assert again == ([], [], [])  # what this platform created stays, reload after reload
        assert w.gateway.gateway_stats.streams_removed == 1
        assert set(w.gateway.service.created) == {"mine/speed", "theirs/speed"}


async def _create(asker: Agent, label: str, output: str) -> Any:
    content = {"action": "create-stream", "label": label, "output": output}
    return await request(asker, GW, content, ontology="dyknow", timeout=5)


async def test_a_stream_the_program_creates_through_the_service_is_its_platforms() -> None:
    """One created by calling the service itself (no agent asked) is this platform's: a
    reload closing the gateway or a revocation leaves it, and no member's share counts it."""
    async with world(max_streams_per_platform=1) as w:
        service = w.gateway.service
        content = {"action": "create-stream", "label": "car/car5/speed", "output": "app/t"}
        assert service.perform(content) == {"label": "app/t", "source": "car/car5/speed"}
        await _create(w.asker, "car/car5/speed", "op/t")
        ended = await w.gateway.set_visibility("private", "closed by the operator")
        assert ended.streams == [("asker@operator", "op/t")]
        assert service.created == {"app/t": "gateway:app/t"} and w.dk.has_label("app/t")
        assert w.gateway.gateway_stats.streams_removed == 1


async def test_going_private_keeps_a_stream_this_platforms_own_stream_reads() -> None:
    async with world() as w:
        local = await w.uav.add(Agent("local"))
        await _create(w.asker, "car/car5/speed", "op/a")  # another platform's
        await _create(local, "op/a", "station/b")  # this platform's, built on it
        here = await subscribe(local, GW, {"label": "station/b"}, ontology="dyknow")
        ended = await w.gateway.set_visibility("private", "closed by the operator")
        assert ended == ([], [], [("asker@operator", "op/a", ["gateway:station/b"])])
        assert w.gateway.gateway_stats.streams_removed == 0
        assert {"gateway:op/a", "gateway:station/b"} <= set(w.dk.processes)
        # station/b still gets its input: a sample pushed now reaches its subscriber
        w.speed.push(7.0, valid_time=T0)
        sample = await here.get(timeout=5)
        assert sample["label"] == "station/b" and sample["samples"][0][0] == 7.0, sample
        # handed to this platform: a later reload does not consider it again
        assert await w.gateway.set_visibility("private", "again") == ([], [], [])
        assert set(w.gateway.service.created) == {"op/a", "station/b"}
        await here.cancel()


async def test_a_stream_removed_by_hand_frees_its_slot_and_its_name() -> None:
    async with world(max_streams=1) as w:
        await _create(w.asker, "car/car5/speed", "op/t")
        w.dk.remove_process("gateway:op/t")  # the operator, by hand
        assert await _create(w.asker, "car/car5/speed", "op/u") == {
            "label": "op/u",
            "source": "car/car5/speed",
        }
        # the user's own process takes the name of the one removed by hand
        w.dk.remove_process("gateway:op/u")
        user = w.dk.add_source("op/u", name="gateway:op/u")
        ended = await w.gateway.set_visibility("private", "closed by the operator")
        assert ended == ([], [], [])  # not the gateway's to remove
        assert w.dk.processes["gateway:op/u"] is user and w.dk.has_label("op/u")
        assert w.gateway.gateway_stats.streams_removed == 0
        assert w.gateway.service.created == {}


async def test_one_platform_holds_at_most_its_share_and_each_freed_slot_is_its_own_again() -> None:
    """Another platform holds at most ``max_*_per_platform`` created streams and
    subscriptions (this platform's own agents are bound by the global limits only); a
    slot freed any way (removed by hand, handed to this platform, cancelled, bounced,
    revoked) counts no more against it."""
    limits = {
        "max_streams": 4,
        "max_streams_per_platform": 1,
        "max_subscriptions": 4,
        "max_subscriptions_per_platform": 1,
    }
    async with world(**limits) as w:
        local = await w.uav.add(Agent("local"))
        gw = w.gateway
        await _create(w.asker, "car/car5/speed", "op/a")
        streams = await refusal(_create(w.asker, "car/car5/speed", "op/b"))
        assert streams == "too many created streams for operator (limit 1 per platform)"
        # the platform's own agents are not bound by it: only by max_streams, as the others
        await _create(local, "car/car5/speed", "mine/a")
        await _create(local, "car/car5/speed", "mine/b")
        feed = await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        subs = await refusal(
            subscribe(w.asker, GW, {"label": "car5-state"}, ontology="dyknow", timeout=5)
        )
        assert subs == "too many subscriptions for operator (limit 1 per platform)"
        mine = [
            await subscribe(local, GW, {"label": "car5-state"}, ontology="dyknow") for _ in range(2)
        ]
        assert (gw.service.held_by("operator"), gw.held_by("operator")) == (1, 1)
        assert gw.gateway_stats.limit_refused == 2
        channel = w.uav.channel
        assert isinstance(channel, InterfaceAgent)
        recs = [r for r in channel.audit.records if r.get("stage") == "gateway"]
        assert [(r["code"], r["sender"], r["reason"]) for r in recs] == [
            ("stream-limit", "asker@operator", f"stream-limit: {streams}"),
            ("subscription-limit", "asker@operator", f"subscription-limit: {subs}"),
        ]
        # the global limits still bound every asker together: 3 streams, 3 subscriptions
        await _create(local, "car/car5/speed", "mine/c")
        full = await refusal(_create(local, "car/car5/speed", "mine/d"))
        assert full == "too many created streams (limit 4)"
        w.dk.remove_process("gateway:mine/c")
        # a stream removed by hand frees its creator's slot
        w.dk.remove_process("gateway:op/a")
        assert gw.service.held_by("operator") == 0
        await _create(w.asker, "car/car5/speed", "op/b")
        assert gw.service.held_by("operator") == 1
        # one handed to this platform (kept at a reload: a stream of this one reads it)
        # is this platform's: its creator may create another
        await _create(local, "op/b", "mine/on-b")
        ended = await gw.set_visibility("private", "closed by the operator")
        assert ended.kept == [("asker@operator", "op/b", ["gateway:mine/on-b"])]
        with pytest.raises(Failed, match="closed by the operator"):
            await feed.get(timeout=5)
        assert (gw.service.held_by("operator"), gw.held_by("operator")) == (0, 0)
        await gw.set_visibility("protected", "opened again")
        w.dk.remove_process("gateway:mine/on-b")
        w.dk.remove_process("gateway:mine/b")
        await _create(w.asker, "car/car5/speed", "op/c")
        # a cancelled subscription frees its slot; so does one whose informs bounce
        feed = await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        await feed.cancel()
        feed = await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        assert gw.held_by("operator") == 1
        bounce = w.asker.message(
            Performative.FAILURE,
            GW,
            "gone",
            ontology="dyknow",
            conversation_id=feed.message.conversation_id,
        )
        await w.asker.send(bounce)
        await eventually(lambda: gw.held_by("operator") == 0, timeout=10)
        feed = await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")
        assert gw.held_by("operator") == 1
        # revoked: what it held is freed (its streams removed, its subscriptions ended)
        interface = w.uav.channel
        assert isinstance(interface, InterfaceAgent)
        assert interface.trust.remove("operator")
        await eventually(lambda: gw.held_by("operator") == 0)
        assert gw.service.held_by("operator") == 0 and "op/c" not in gw.service.created
        for m in mine:
            await m.cancel()


def _remove(asker: Agent, label: Any) -> Any:
    content = {"action": "remove-stream", "label": label}
    return request(asker, GW, content, ontology="dyknow", timeout=5)


async def test_a_member_removes_the_streams_it_created_and_no_other() -> None:
    """Any agent of the platform that created a stream may remove it: its subscribers see
    it end, its slot is free at once, one record audits it; another platform's stream, a
    stream not created through the gateway and a label not here are refused (counted and
    audited when another platform asks); this platform's own agents may remove any."""
    async with world(max_streams_per_platform=1) as w:
        local = await w.uav.add(Agent("local"))
        other = await w.operator.add(Agent("other"))
        gw = w.gateway
        await _create(w.asker, "car/car5/speed", "op/t")
        await _create(local, "car/car5/speed", "mine/t")
        theirs = await subscribe(w.asker, GW, {"label": "op/t"}, ontology="dyknow")
        here = await subscribe(local, GW, {"label": "op/t"}, ontology="dyknow")
        told = [
            await refusal(_remove(w.asker, "mine/t")),
            await refusal(_remove(w.asker, "car/car5/speed")),
            await refusal(_remove(w.asker, "car/car9/speed")),
            await refusal(_remove(w.asker, ["op/t"])),
        ]
        assert told == [
            "stream 'mine/t' was not created by operator",
            "stream 'car/car5/speed' was not created by a create-stream",
            "unknown label 'car/car9/speed' (known labels: car/car5/speed, car5-state, "
            "mine/t, op/t)",
            "field 'label': Input should be a valid string",
        ]
        # an action, not a query; never answered at once, on the loop or zenoh's thread
        ref = query_ref(
            w.asker, GW, {"action": "remove-stream", "label": "op/t"}, ontology="dyknow"
        )
        assert await refusal(ref) == "remove-stream is an action: ask for it with FIPA-Request"
        message = w.asker.message(
            Performative.REQUEST,
            GW,
            {"action": "remove-stream", "label": "op/t"},
            ontology="dyknow",
        )
        assert gw.answer_at_once(message) is LATER and gw.answer_on_thread(message) is LATER
        assert w.dk.has_label("op/t") and gw.gateway_stats.streams_removed == 0
        # another agent of the creator's platform removes it
        assert await _remove(other, "op/t") == {"removed": "op/t"}
        for feed in (theirs, here):
            with pytest.raises(SubscriptionEnded):  # the stream's end: a clean one
                await feed.get(timeout=5)
        assert not w.dk.has_label("op/t") and "gateway:op/t" not in w.dk.processes
        assert gw.service.held_by("operator") == 0 and gw.gateway_stats.streams_removed == 1
        await eventually(lambda: gw.subscriptions == {})
        # its slot free at once: it creates again, and removing the one gone is refused
        await _create(w.asker, "car/car5/speed", "op/u")
        gone = await refusal(_remove(w.asker, "op/t"))
        assert gone.startswith("unknown label 'op/t' (known labels: ")
        # this platform's own agents remove another platform's stream; a source is refused
        # them too, neither counted nor audited
        assert await _remove(local, "op/u") == {"removed": "op/u"}
        mine = await refusal(_remove(local, "car5-state"))
        assert mine == "stream 'car5-state' was not created by a create-stream"
        stats = gw.gateway_stats
        assert (stats.not_creator_refused, stats.not_created_refused) == (1, 1)
        assert (stats.unknown_label_refused, stats.streams_removed) == (2, 2)
        channel = w.uav.channel
        assert isinstance(channel, InterfaceAgent)
        recs = [r for r in channel.audit.records if r.get("stage") == "gateway"]
        assert [(r["verdict"], r["code"], r["sender"], r.get("stream")) for r in recs] == [
            ("refused", "not-creator", "asker@operator", None),
            ("refused", "not-created", "asker@operator", None),
            ("refused", "unknown-label", "asker@operator", None),
            ("ended", "remove-stream", "other@operator", "op/t"),
            ("refused", "unknown-label", "asker@operator", None),
            ("ended", "remove-stream", "local@uav-a", "op/u"),
        ], recs
        assert recs[0]["reason"] == f"not-creator: {told[0]}"
        assert recs[1]["reason"] == f"not-created: {told[1]}"
        ended = recs[3]
        assert (ended["from"], ended["to"], ended["creator"]) == (
            "operator",
            "operator",
            "asker@operator",
        )
        assert ended["reason"] == (
            "gateway stream 'op/t' created by asker@operator removed: asked by other@operator"
        )
        assert (recs[5]["to"], recs[5]["creator"]) == ("operator", "asker@operator")


async def test_a_stream_its_creator_removes_that_a_process_here_reads_is_kept() -> None:
    """Removed by its creator, a stream a staying process reads is kept, handed to this
    platform as at a reload: what is built on it keeps its input, the slot is free."""
    async with world(max_streams_per_platform=1) as w:
        local = await w.uav.add(Agent("local"))
        await _create(w.asker, "car/car5/speed", "op/a")
        await _create(local, "op/a", "station/b")
        here = await subscribe(local, GW, {"label": "station/b"}, ontology="dyknow")
        assert await _remove(w.asker, "op/a") == {"kept": "op/a"}
        assert w.gateway.service.held_by("operator") == 0
        assert w.gateway.gateway_stats.streams_removed == 0
        w.speed.push(7.0, valid_time=T0)
        sample = await here.get(timeout=5)
        assert sample["label"] == "station/b" and sample["samples"][0][0] == 7.0, sample
        # this platform's now: its first creator may not remove it, but create another
        told = await refusal(_remove(w.asker, "op/a"))
        assert told == "stream 'op/a' was not created by operator"
        await _create(w.asker, "car/car5/speed", "op/c")
        channel = w.uav.channel
        assert isinstance(channel, InterfaceAgent)
        recs = [r for r in channel.audit.records if r.get("stage") == "gateway"]
        assert [(r["verdict"], r["code"], r.get("creator")) for r in recs] == [
            ("kept", "remove-stream", "asker@operator"),
            ("refused", "not-creator", None),
        ]
        assert recs[0]["reason"] == (
            "gateway stream 'op/a' created by asker@operator kept: read by gateway:station/b"
            " (now this platform's): asked by asker@operator"
        )
        await here.cancel()


async def test_a_stream_handed_to_this_platform_at_going_private_is_not_its_creators() -> None:
    async with world() as w:
        local = await w.uav.add(Agent("local"))
        await _create(w.asker, "car/car5/speed", "op/a")
        await _create(local, "op/a", "station/b")
        ended = await w.gateway.set_visibility("private", "closed by the operator")
        assert ended.kept == [("asker@operator", "op/a", ["gateway:station/b"])]
        await w.gateway.set_visibility("protected", "opened again")
        told = await refusal(_remove(w.asker, "op/a"))
        assert told == "stream 'op/a' was not created by operator"
        assert w.dk.has_label("op/a") and w.gateway.gateway_stats.not_creator_refused == 1
        # this platform's agents may: station/b, which read it, loses its input then
        assert await _remove(local, "station/b") == {"removed": "station/b"}
        assert await _remove(local, "op/a") == {"removed": "op/a"}
        assert w.gateway.service.created == {}


def test_the_gateways_limits_are_counts_named_when_wrong() -> None:
    dk = DyKnowInstance("uav-a")
    for key in (
        "max_streams",
        "max_streams_per_platform",
        "max_subscriptions",
        "max_subscriptions_per_platform",
    ):
        with pytest.raises(ValueError, match=f"^{key}: must be a whole number of at least 0"):
            GatewayAgent(dk, **{key: -1})
    with pytest.raises(ValueError, match=r"max_streams_per_platform: .* not 2\.5"):
        GatewayService(dk, max_streams_per_platform=2.5)  # type: ignore[arg-type]


async def test_a_re_registration_that_fails_leaves_the_gateway_and_its_entry_as_they_were() -> None:
    async with world() as w:
        df = w.uav.df
        assert df is not None
        theirs = await subscribe(w.asker, GW, {"label": "car/car5/speed"}, ontology="dyknow")

        async def broken(*args: Any) -> None:
            raise RuntimeError("injected: the directory event cannot be sent")

        df._changed = broken  # type: ignore[method-assign]
        try:
            with pytest.raises(RuntimeError, match="injected"):
                await w.gateway.set_visibility("private", "closed by the operator")
        finally:
            del df._changed
        assert w.gateway.visibility == "protected"
        (entry,) = df.search(provider=GW)
        assert entry.visibility == "protected"
        assert len(w.gateway.subscriptions) == 1  # not ended: the gateway stays open
        w.speed.push(1.0, valid_time=T0)
        assert (await theirs.get(timeout=5))["label"] == "car/car5/speed"
        # and the same change again, now told, applies
        ended = await w.gateway.set_visibility("private", "closed by the operator")
        assert ended.subscriptions == [("asker@operator", "car/car5/speed")]
        (entry,) = df.search(provider=GW)
        assert entry.visibility == "private" == w.gateway.visibility
        with pytest.raises(Failed):
            for _ in range(100):
                await theirs.get(timeout=5)


async def test_a_cancel_of_no_subscription_names_its_conversation_bounded_on_one_line() -> None:
    """A cancel in a conversation holding no subscription fails naming the conversation
    id the asker chose: on one line, cut at 64 characters (docs/security.md); a short
    printable one as it is."""
    async with world() as w:
        forged = 'c\n{"verdict": "accepted"}\x1b[2J' + "c" * 20_000
        told = []
        for conv in (forged, "c-none"):
            cancel = w.asker.message(
                Performative.CANCEL, GW, None, ontology="dyknow", conversation_id=conv
            )
            answer = await w.asker.ask(cancel, timeout=5)
            assert answer.performative is Performative.FAILURE
            told.append(str(answer.content))
        assert told[0].startswith('no subscription in conversation c\\x0a{"verdict"')
        assert told[0].endswith("… (20029 characters, 19971 left out)")
        assert "\n" not in told[0] and "\x1b" not in told[0] and len(told[0]) < 200
        assert told[1] == "no subscription in conversation c-none"


# -- the Gateway: reserved labels are not even named to another platform --------------------


@pytest.mark.parametrize(
    "content",
    [
        {"action": "query", "label": "nope"},  # the quick query
        {"action": "query", "label": "nope", "kind": "at", "t": 1.0},  # the models' path
        {"action": "create-stream", "label": "nope", "output": "out"},
    ],
)
async def test_an_unknown_label_refusal_names_no_reserved_label_to_another_platform(
    content: dict[str, Any],
) -> None:
    from agents import Refused

    async with world(visibility="protected") as w:
        w.dk.add_source("import/uav-c/secret")
        with pytest.raises(Refused) as refused:
            await w.ask(content)
        reason = str(refused.value)
        assert "unknown label 'nope'" in reason
        assert "car5-state" in reason  # what it may see is still listed
        assert "import/" not in reason


async def test_an_unknown_label_subscription_names_no_reserved_label_to_another_platform() -> None:
    from agents import Refused, subscribe

    async with world(visibility="protected") as w:
        w.dk.add_source("import/uav-c/secret")
        with pytest.raises(Refused) as refused:
            await subscribe(w.asker, GW, {"label": "nope"}, ontology="dyknow", timeout=5)
        assert "import/" not in str(refused.value)


# -- get-latest of many labels: one clock reading, no Answer per label ----------------------


async def test_latest_of_many_labels_answers_as_one_latest_per_label() -> None:
    """`latest_contents` gives what `answer_content(latest(label))` gives, label by label."""
    from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock, UnknownLabelError
    from federation._gateway_service import answer_content, latest_contents

    t0 = 1_000 * NS_PER_S
    clock = ManualClock(t0)
    async with DyKnowInstance("u", clock=clock) as dk:
        scalar, rich, _, bumped, future = (
            dk.add_source(label) for label in ("s", "r", "e", "b", "f")
        )
        scalar.push(1.5, valid_time=t0 - 5)
        scalar.push(2.5, valid_time=t0 - 9)  # older valid time: not the latest
        rich.push({"pos": (1, 2)}, valid_time=t0 - 1)  # a tuple inside: made JSON
        bumped.push("x")
        bumped.push("y")  # the same clock reading: stamped 1 ns later, seen now
        future.push(7, available_time=t0 + NS_PER_S)  # not known before the clock gets there
        labels = ["s", "r", "e", "b", "f", "s"]
        want = [answer_content(dk.latest(label)) for label in labels]
        assert latest_contents(dk, labels) == want
        # the cases above are what they say
        assert [c["samples"][0][0] if c["samples"] else None for c in want] == [
            1.5,
            {"pos": [1, 2]},
            None,
            "y",
            None,
            1.5,
        ]
        with pytest.raises(UnknownLabelError) as info:
            latest_contents(dk, ["s", "nope"])
        assert info.value.label == "nope"
