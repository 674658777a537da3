"""Interaction protocols, both sides: FIPA-Request, -Query, -Subscribe, -Contract-Net."""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import uuid
from collections.abc import AsyncIterator, Iterator
from typing import Any

import pytest

from agents import (
    FIPA_REQUEST,
    ACLMessage,
    Agent,
    AgentPlatform,
    ConversationError,
    Failed,
    Failure,
    MemoryHub,
    MessageTemplate,
    NotUnderstood,
    Performative,
    Proposal,
    Publisher,
    Refuse,
    Refused,
    ReplyTimeout,
    SubscriptionEnded,
    contract_net,
    on,
    on_accept_proposal,
    on_cfp,
    on_query,
    on_reject_proposal,
    on_request,
    query_if,
    query_ref,
    request,
    subscribe,
)
from agents.transports import (
    MqttConfig,
    MqttTransport,
    Transport,
    ZenohConfig,
    ZenohTransport,
    free_tcp_port,
)

P = Performative


_KIND: contextvars.ContextVar[tuple[str, Any]] = contextvars.ContextVar(
    "transport_kind", default=("memory", None)
)


@pytest.fixture(params=["memory", "zenoh", "mqtt"], autouse=True)
def transport_kind(request: pytest.FixtureRequest) -> Iterator[str]:
    """Run every protocol test over each transport: the same semantics on all three."""
    broker = request.getfixturevalue("mosquitto") if request.param == "mqtt" else None
    token = _KIND.set((request.param, broker))
    try:
        yield request.param
    finally:
        _KIND.reset(token)


def _transports(n: int) -> list[Transport]:
    kind, broker = _KIND.get()
    if kind == "memory":
        hub = MemoryHub()
        return [hub.transport() for _ in range(n)]
    if kind == "zenoh":
        seed = free_tcp_port()
        return [ZenohTransport(ZenohConfig.loopback(seed))] + [
            ZenohTransport(ZenohConfig.loopback(free_tcp_port(), connect=[seed]))
            for _ in range(n - 1)
        ]
    host, port = broker
    return [MqttTransport(MqttConfig(host=host, port=port, keepalive=5)) for _ in range(n)]


@contextlib.asynccontextmanager
async def platforms(*names: str) -> AsyncIterator[list[AgentPlatform]]:
    """Platforms on the test's transport; on exit, checks that no task is left behind."""
    kind, _ = _KIND.get()
    federation = f"t{uuid.uuid4().hex[:8]}"  # tests sharing a broker never see each other
    async with contextlib.AsyncExitStack() as stack:
        out = []
        for name, transport in zip(names, _transports(len(names)), strict=True):
            await stack.enter_async_context(transport)
            out.append(
                await stack.enter_async_context(
                    AgentPlatform(name, transport, federation=federation, query_timeout=0.3)
                )
            )
        if kind != "memory":
            await _all_see_each_other(out)
        yield out
    assert asyncio.all_tasks() == {asyncio.current_task()}


async def _all_see_each_other(ps: list[AgentPlatform]) -> None:
    """Wait until every platform sees every other's liveliness token.

    A platform declares its token after its inbox; zenoh routes declarations in order, so
    once the token is seen, messages to that inbox are routed too.
    """
    names = {p.name for p in ps}
    async with asyncio.timeout(10):
        for p in ps:
            watch = await p.transport.watch_presence(p.key("alive", "*"))
            seen: set[str] = set()
            try:
                while not names <= seen:
                    change = await watch.get()
                    if change.alive:
                        seen.add(change.key.rpartition("/")[2])
            finally:
                watch.close()


# -- FIPA-Request --------------------------------------------------------------------------


class Thermometer(Agent):
    """Answers requests in the weather ontology in every way the protocol allows."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.hold = asyncio.Event()

    @on_request("weather")
    async def read(self, m: ACLMessage) -> Any:
        what = m.content
        if what == "temperature":
            return {"celsius": 21.5}
        if what == "humidity":
            raise Refuse("no hygrometer")
        if what == "pressure":
            raise Failure("barometer broken")
        if what == "wind":
            raise KeyError("anemometer")
        if what == "never":
            await self.hold.wait()
        return None

    @on_request("slow-weather", agree=True, concurrent=True)
    async def slow(self, m: ACLMessage) -> Any:
        if m.content == "refuse-late":
            raise Refuse("changed my mind")
        return "done"


async def test_request_returns_the_inform_content() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        await p.add(Thermometer("thermo"))
        a = await p.add(Agent("a"))
        assert await request(a, "thermo@p", "temperature", ontology="weather") == {"celsius": 21.5}
        assert await request(a, "thermo@p", "nothing", ontology="weather") is None


async def test_a_request_starts_when_awaited_and_a_dropped_one_sends_nothing() -> None:
    """`request` is a plain call returning the exchange: nothing is composed, registered
    or sent before it is awaited, and one closed unawaited leaves nothing behind."""
    async with asyncio.timeout(5), platforms("p") as [p]:
        await p.add(Thermometer("thermo"))
        a = await p.add(Agent("a"))
        sent = p.stats.local
        dropped = request(a, "thermo@p", "temperature", ontology="weather")
        pending = request(a, "thermo@p", "temperature", ontology="weather")
        assert asyncio.iscoroutine(pending)
        dropped.close()
        assert p.stats.local == sent and not a._by_conv and not a._by_reply
        assert await pending == {"celsius": 21.5}
        assert not a._by_conv and not a._by_reply  # closed once answered


class Tagging(Agent):
    """An agent whose own `message` files its messages under a conversation of its naming."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.made: list[ACLMessage] = []

    def message(
        self, performative: Any, receivers: Any, content: Any = None, **fields: Any
    ) -> ACLMessage:
        fields["conversation_id"] = f"tag-{fields['conversation_id']}"
        made = super().message(performative, receivers, content, **fields)
        self.made.append(made)
        return made


async def test_a_request_is_made_by_the_agents_own_message_its_class_or_its_own() -> None:
    """An agent's `message`, overridden in its class or set on the agent itself, makes the
    request, and the answer is matched in the conversation that message names."""
    async with asyncio.timeout(5), platforms("p") as [p]:
        await p.add(Thermometer("thermo"))
        tagging = await p.add(Tagging("tagging"))
        assert await request(tagging, "thermo@p", "temperature", ontology="weather") == {
            "celsius": 21.5
        }
        assert [m.conversation_id[:6] for m in tagging.made] == ["tag-c-"]
        plain = await p.add(Agent("plain"))
        made: list[ACLMessage] = []
        message = plain.message

        def own(*args: Any, **fields: Any) -> ACLMessage:
            made.append(message(*args, **fields))
            return made[-1]

        plain.message = own  # type: ignore[method-assign]
        answer = request(plain, "thermo@p", "temperature", ontology="weather", conversation_id="q1")
        assert await answer == {"celsius": 21.5}
        assert [m.conversation_id for m in made] == ["q1"]


@pytest.mark.parametrize(
    ("what", "error", "says"),
    [
        ("humidity", Refused, "no hygrometer"),
        ("pressure", Failed, "barometer broken"),
        ("wind", Failed, "KeyError"),
    ],
)
async def test_request_refused_or_failed_raises_with_the_message(
    what: str, error: type[Exception], says: str
) -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        await p.add(Thermometer("thermo"))
        a = await p.add(Agent("a"))
        with pytest.raises(error) as err:
            await request(a, "thermo@p", what, ontology="weather")
        message = err.value.message  # type: ignore[attr-defined]
        assert message is not None and says in str(message.content)
        assert message.sender == "thermo@p" and message.protocol == FIPA_REQUEST
        assert says in str(err.value)


async def test_request_with_agree_then_inform() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        await p.add(Thermometer("thermo"))
        a = await p.add(Agent("a"))
        agreed: list[ACLMessage] = []
        result = await request(a, "thermo@p", "x", ontology="slow-weather", on_agree=agreed.append)
        assert result == "done"
        assert [m.performative for m in agreed] == [P.AGREE]
        with pytest.raises(Failed, match="changed my mind"):  # after agree: failure, not refuse
            await request(a, "thermo@p", "refuse-late", ontology="slow-weather")


async def test_request_nobody_understands_raises_not_understood() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        await p.add(Thermometer("thermo"))
        a = await p.add(Agent("a"))
        with pytest.raises(NotUnderstood) as err:
            await request(a, "thermo@p", "x", ontology="astrology")
        assert err.value.message is not None
        assert err.value.message.performative is P.NOT_UNDERSTOOD


async def test_request_without_answer_times_out_quickly() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        t = await p.add(Thermometer("thermo"))
        a = await p.add(Agent("a"))
        with pytest.raises(ReplyTimeout) as err:
            await request(a, "thermo@p", "never", ontology="weather", timeout=0.05)
        assert err.value.message is not None and err.value.message.content == "never"
        t.hold.set()  # its late inform is dropped by the initiator
        assert await request(a, "thermo@p", "temperature", ontology="weather") == {"celsius": 21.5}


async def test_request_across_platforms() -> None:
    async with asyncio.timeout(5), platforms("uav-a", "uav-b") as [pa, pb]:
        await pa.add(Thermometer("thermo"))
        b = await pb.add(Agent("b"))
        assert await request(b, "thermo@uav-a", "temperature", ontology="weather") == {
            "celsius": 21.5
        }
        with pytest.raises(Refused):
            await request(b, "thermo@uav-a", "humidity", ontology="weather")
        with pytest.raises(Failed, match="no agent"):
            await request(b, "ghost@uav-a", "x")


async def test_a_plain_function_responder() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        svc = await p.add(Agent("svc"))

        @on_request("math")
        async def double(m: ACLMessage) -> Any:
            return 2 * m.content  # type: ignore[operator]

        svc.add_responder(double)
        a = await p.add(Agent("a"))
        assert await request(a, "svc@p", 21, ontology="math") == 42


# -- FIPA-Query ----------------------------------------------------------------------------


class Oracle(Agent):
    facts = {"sky": "blue", "grass": "green"}

    @on_query("colors")
    async def answer(self, m: ACLMessage) -> Any:
        if m.performative is P.QUERY_IF:
            if m.content == "odd":
                return "maybe"
            return m.content in self.facts
        if m.content not in self.facts:
            raise Failure(f"unknown thing {m.content!r}")
        return self.facts[m.content]  # type: ignore[index]

    @on_query("secrets")
    async def secret(self, m: ACLMessage) -> Any:
        raise Refuse("classified")


async def test_query_ref_and_query_if() -> None:
    async with asyncio.timeout(5), platforms("p", "q") as [p, q]:
        await p.add(Oracle("oracle"))
        for platform in (p, q):
            a = await platform.add(Agent("a"))
            assert await query_ref(a, "oracle@p", "sky", ontology="colors") == "blue"
            assert await query_if(a, "oracle@p", "grass", ontology="colors") is True
            assert await query_if(a, "oracle@p", "sea", ontology="colors") is False
            with pytest.raises(Failed, match="unknown thing"):
                await query_ref(a, "oracle@p", "sea", ontology="colors")
            with pytest.raises(Refused, match="classified"):
                await query_ref(a, "oracle@p", "x", ontology="secrets")
            with pytest.raises(ConversationError, match="not true/false"):
                await query_if(a, "oracle@p", "odd", ontology="colors")


async def test_query_times_out() -> None:
    class Mute(Agent):
        @on(MessageTemplate(P.QUERY_REF))
        async def ignore(self, m: ACLMessage) -> None:
            pass

    async with asyncio.timeout(5), platforms("p") as [p]:
        await p.add(Mute("mute"))
        a = await p.add(Agent("a"))
        with pytest.raises(ReplyTimeout):
            await query_ref(a, "mute@p", "x", timeout=0.05)


# -- FIPA-Subscribe ------------------------------------------------------------------------


class Station(Agent):
    """Publishes readings; refuses subscriptions to what it does not measure."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.readings = Publisher(self, ontology="weather", accept=self.accept)

    def accept(self, m: ACLMessage) -> Any:
        if m.content not in ("temperature", "wind"):
            raise Refuse(f"I do not measure {m.content}")
        return m.content  # kept as the subscriber's data: what it wants

    async def emit(self, what: str, value: Any) -> int:
        return await self.readings.publish(value, where=lambda s: s.data == what)


async def test_subscribe_gets_informs_until_cancelled() -> None:
    async with asyncio.timeout(5), platforms("p", "q") as [p, q]:
        st = await p.add(Station("station"))
        for platform in (p, q):
            a = await platform.add(Agent("a"))
            stream = await subscribe(a, "station@p", "temperature", ontology="weather")
            assert stream.agree.performative is P.AGREE and len(st.readings) == 1
            assert await st.emit("temperature", 20) == 1
            assert await st.emit("wind", 5) == 0  # nobody wants wind
            await st.emit("temperature", 21)
            got = [await stream.get(timeout=2), await stream.get(timeout=2)]
            assert got == [20, 21]
            await stream.cancel()  # waits for the station to confirm
            assert len(st.readings) == 0 and stream.ended
            assert [x async for x in stream] == []
            await a.stop()


async def test_subscription_as_async_with_and_async_for() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        st = await p.add(Station("station"))
        a = await p.add(Agent("a"))
        got = []
        async with await subscribe(a, "station@p", "wind", ontology="weather") as stream:
            for v in (1, 2, 3):
                await st.emit("wind", v)
            async for value in stream:
                got.append(value)
                if len(got) == 3:
                    break
        assert got == [1, 2, 3]
        assert len(st.readings) == 0  # leaving the block cancelled it


async def test_cancel_from_another_task_ends_a_reader() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        st = await p.add(Station("station"))
        a = await p.add(Agent("a"))
        stream = await subscribe(a, "station@p", "wind", ontology="weather")

        got: list[Any] = []
        first = asyncio.Event()

        async def read() -> None:
            async for x in stream:
                got.append(x)
                first.set()

        reader = asyncio.ensure_future(read())
        await st.emit("wind", 1)
        await first.wait()
        await stream.cancel()
        await reader
        assert got == [1]


async def test_the_responder_can_end_a_subscription() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        st = await p.add(Station("station"))
        a1 = await p.add(Agent("a1"))
        a2 = await p.add(Agent("a2"))
        clean = await subscribe(a1, "station@p", "wind", ontology="weather")
        failing = await subscribe(a2, "station@p", "wind", ontology="weather")
        await st.emit("wind", 1)
        await st.readings.end("a1@p")  # cancel: a clean end
        await st.readings.end("a2@p", reason="station shutting down")  # failure
        assert len(st.readings) == 0
        assert [x async for x in clean] == [1]
        assert await failing.get(timeout=2) == 1
        with pytest.raises(Failed, match="shutting down"):
            await failing.get(timeout=2)
        with pytest.raises(SubscriptionEnded):
            await failing.get(timeout=2)


async def test_publisher_end_sends_cancel_to_everyone() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        st = await p.add(Station("station"))
        a = await p.add(Agent("a"))
        streams = [
            await subscribe(a, "station@p", w, ontology="weather") for w in ("wind", "temperature")
        ]
        await st.readings.end()
        for s in streams:
            assert [x async for x in s] == []
        assert len(st.readings) == 0


async def test_refused_subscription() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        await p.add(Station("station"))
        a = await p.add(Agent("a"))
        with pytest.raises(Refused, match="do not measure rain"):
            await subscribe(a, "station@p", "rain", ontology="weather")
        with pytest.raises(NotUnderstood):
            await subscribe(a, "station@p", "rain", ontology="astrology")
        assert not a._by_conv and not a._by_reply


async def test_subscribe_without_answer_times_out() -> None:
    class Mute(Agent):
        @on(MessageTemplate(P.SUBSCRIBE))
        async def ignore(self, m: ACLMessage) -> None:
            pass

    async with asyncio.timeout(5), platforms("p") as [p]:
        await p.add(Mute("mute"))
        a = await p.add(Agent("a"))
        with pytest.raises(ReplyTimeout):
            await subscribe(a, "mute@p", timeout=0.05)
        assert not a._by_conv and not a._by_reply


async def test_cancel_without_confirmation_does_not_hang() -> None:
    class Forgetful(Agent):
        def __init__(self, name: str) -> None:
            super().__init__(name)
            self.pub = Publisher(self)

    async with asyncio.timeout(5), platforms("p") as [p]:
        f = await p.add(Forgetful("f"))
        a = await p.add(Agent("a"))
        stream = await subscribe(a, "f@p")
        f.pub.close()  # stops answering cancel: the not-understood it now gets ends the wait
        await stream.cancel(timeout=0.2)
        assert stream.ended


# -- FIPA-Contract-Net -----------------------------------------------------------------------


class Carrier(Agent):
    """Bids a price for a delivery; performs it when accepted."""

    def __init__(
        self,
        name: str,
        price: float | None,
        *,
        fail: bool = False,
        wait: asyncio.Event | None = None,
        done: asyncio.Event | None = None,
    ) -> None:
        super().__init__(name)
        self.price = price
        self.fail = fail
        self.wait = wait
        self.done = done
        self.rejected: list[ACLMessage] = []
        self.got_reject = asyncio.Event()
        self.accepted: list[ACLMessage] = []

    @on_cfp("delivery", concurrent=True)
    async def bid(self, cfp: ACLMessage) -> Any:
        if self.wait is not None:
            await self.wait.wait()
        if self.price is None:
            raise Refuse("busy")
        return {"price": self.price}

    @on_accept_proposal("delivery", concurrent=True)
    async def deliver(self, m: ACLMessage) -> Any:
        self.accepted.append(m)
        if self.wait is not None:
            await self.wait.wait()
        if self.done is not None:
            await self.done.wait()
        if self.fail:
            raise Failure("truck broke down")
        return {"delivered": m.content}

    @on_reject_proposal("delivery")
    async def lost(self, m: ACLMessage) -> None:
        self.rejected.append(m)
        self.got_reject.set()


class LateCarrier(Carrier):
    """A carrier that tells when its proposal has gone out."""

    def __init__(self, name: str, price: float, *, wait: asyncio.Event) -> None:
        super().__init__(name, price, wait=wait)
        self.proposed = asyncio.Event()

    async def send(self, message: ACLMessage) -> None:
        await super().send(message)
        if message.performative is P.PROPOSE:
            self.proposed.set()


def cheapest(proposals: list[Proposal]) -> list[Proposal]:
    return sorted(proposals, key=lambda p: p.content["price"])[:1]  # type: ignore[call-overload, index]


async def test_contract_net_awards_the_best_and_rejects_the_others() -> None:
    async with asyncio.timeout(5), platforms("p", "q") as [p, q]:
        cheap = await p.add(Carrier("cheap", 10))
        dear = await q.add(Carrier("dear", 30))
        await p.add(Carrier("busy", None))
        boss = await p.add(Agent("boss"))
        result = await contract_net(
            boss,
            ["cheap@p", "dear@q", "busy@p"],
            "parcel",
            deadline=1.0,
            select=cheapest,
            ontology="delivery",
        )
        assert {x.participant for x in result.proposals} == {"cheap@p", "dear@q"}
        assert list(result.refused) == ["busy@p"] and result.refused["busy@p"].content == "busy"
        assert [x.participant for x in result.accepted] == ["cheap@p"]
        assert result.results == {"cheap@p": {"delivered": {"price": 10}}}
        assert (
            not result.failures
            and not result.no_answer
            and not result.no_result
            and not result.late
        )
        assert len(cheap.accepted) == 1
        await dear.got_reject.wait()
        assert dear.rejected[0].performative is P.REJECT_PROPOSAL


async def test_contract_net_accepted_participant_fails() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        await p.add(Carrier("clumsy", 5, fail=True))
        boss = await p.add(Agent("boss"))
        result = await contract_net(boss, ["clumsy@p"], "vase", deadline=1.0, ontology="delivery")
        assert list(result.failures) == ["clumsy@p"]
        assert result.failures["clumsy@p"].content == "truck broke down"
        assert not result.results


async def test_contract_net_ignores_a_late_proposal() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        release_late = asyncio.Event()
        late = await p.add(LateCarrier("late", 1, wait=release_late))  # cheapest, but late
        # The on-time winner finishes only after the late proposal has gone out, so the
        # initiator is still listening when it arrives.
        ontime = await p.add(Carrier("ontime", 20, done=late.proposed))
        boss = await p.add(Agent("boss"))

        def select(proposals: list[Proposal]) -> list[Proposal]:
            release_late.set()  # the deadline is over: now let the late one answer
            return cheapest(proposals)

        result = await contract_net(
            boss, ["late@p", "ontime@p"], "parcel", deadline=0.1, select=select, ontology="delivery"
        )
        assert [x.participant for x in result.proposals] == ["ontime@p"]
        assert result.no_answer == ["late@p"]
        assert result.results == {"ontime@p": {"delivered": {"price": 20}}}
        assert [(m.sender, m.performative) for m in result.late] == [("late@p", P.PROPOSE)]
        assert not late.accepted and not late.rejected  # ignored: neither accepted nor rejected
        assert len(ontime.accepted) == 1


async def test_contract_net_with_silent_participants_and_no_result() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        never = asyncio.Event()
        await p.add(Carrier("silent", 1, wait=never))
        slow = await p.add(Carrier("slow", 2, done=never))
        boss = await p.add(Agent("boss"))
        result = await contract_net(
            boss,
            ["silent@p", "slow@p"],
            "x",
            deadline=0.05,
            ontology="delivery",
            result_timeout=0.05,
        )
        assert result.no_answer == ["silent@p"]
        assert [x.participant for x in result.accepted] == ["slow@p"]
        assert result.no_result == ["slow@p"]
        assert len(slow.accepted) == 1


async def test_contract_net_with_nobody() -> None:
    async with asyncio.timeout(5), platforms("p") as [p]:
        boss = await p.add(Agent("boss"))
        result = await contract_net(boss, [], "x", deadline=0.05)
        assert not result.proposals and not result.accepted
        result = await contract_net(boss, ["ghost@p"], "x", deadline=1.0)
        assert list(result.refused) == ["ghost@p"]  # the platform failed it for the ghost
