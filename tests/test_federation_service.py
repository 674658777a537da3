"""The DyKnow Federation service: streams, queries, global requests, label search, membership.

Three platforms (uav-a, uav-b, operator) on one MemoryHub, each with its Interface Agent,
DyKnow instance and Federation Agent; the ontology and the export proxy are fakes (the
service only needs the small protocols it declares).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Awaitable
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum
from types import SimpleNamespace
from typing import Any

import orjson
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agents import (
    FIPA_REQUEST,
    ACLMessage,
    Agent,
    AgentPlatform,
    Failed,
    HandedOver,
    MessageTemplate,
    Performative,
    Refused,
    ServiceDescription,
    Visibility,
    new_id,
    on,
    query_ref,
    request,
    subscribe,
)
from agents._interface import InterfaceAgent
from agents._platform import REFUSAL_AUDIT_INTERVAL, REFUSALS_ONE_BY_ONE
from agents._security import KeyPair, TrustStore
from agents.transports import MemoryHub, MemoryTransport
from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock, Policy, Source, UnknownLabelError
from federation._batch import pack_batch, read_batch
from federation._gateway_service import jsonable
from federation._service import (
    FEDERATION_SERVICE_TYPE,
    ONTOLOGY,
    FederationAgent,
    MembershipEvent,
)
from federation._service_content import ContentError, GetLatest, latest_labels, parse_request
from federation._sharing import Sharing, SharingRule, SharingSettings
from ontology import LabelMapping, PlatformLabels, Vocabulary
from tests.test_proxies import until

FED = "t"
T0 = 1000 * NS_PER_S  # every instance's now when a test starts
WAIT = 2.0  # the bound on any single wait; every test finishes far below it
P = Performative

# Each platform's own local labels for the semantic labels it provides.
TABLES = {
    "uav-a": {
        "heli-max-speed": "a/limits/max_speed",
        "heli-altitude": "a/state/altitude",
        "car5-state": "a/cars/car5/state",
    },
    "uav-b": {
        "heli-max-speed": "b.max-speed",
        "heli-altitude": "b.alt",
        "car5-state": "b.car5",
    },
    "operator": {"picture": "op/picture"},
}


# -- fakes for the ontology and the export proxy ---------------------------------------------


class UnknownSemantic(KeyError):
    """Like the ontology's UnknownSemanticLabel: a KeyError, a short code in ``reason``."""

    def __init__(self, label: str) -> None:
        self.reason = "not-mapped"
        super().__init__(f"semantic label {label!r} has no mapping on this platform")

    def __str__(self) -> str:
        return str(self.args[0])


class FakeTranslator:
    def __init__(self, table: dict[str, str]) -> None:
        self.table = table

    def to_local(self, semantic: str) -> str:
        try:
            return self.table[semantic]
        except KeyError:
            raise UnknownSemantic(semantic) from None

    def to_semantic(self, local: str) -> str:
        return {v: k for k, v in self.table.items()}[local]

    def provides(self) -> list[str]:
        return list(self.table)


class FakeSearch:
    """Blue car5 is known; an unmatched parenthesis is an error naming its position."""

    def find(self, formula: str) -> list[str]:
        opened: list[int] = []
        for i, c in enumerate(formula):
            if c == "(":
                opened.append(i)
            elif c == ")":
                if not opened:
                    raise ValueError(f"unexpected ')' at position {i}")
                opened.pop()
        if opened:
            raise ValueError(f"'(' at position {opened[-1]} is never closed")
        return ["car5-state"] if "blue" in formula else []


@dataclass
class FakeExport:
    local: str
    semantic: str
    receiver: str
    policy: Policy
    history: int = 0
    stopped: bool = False
    why: str | None = None  # told to its receiver when stopped


@dataclass
class FakeExporter:
    """Records exports; async to start (as the proxy is), sync to stop."""

    started: list[FakeExport] = field(default_factory=list)
    fail_for: str | None = None
    missing: set[str] = field(default_factory=set)  # local labels with no stream behind
    delay: float = 0.0  # s a start takes (the proxy's awaits a session): requests overlap

    async def start_exporting(
        self, local: str, semantic: str, receiver: str, policy: Policy, *, history: int = 0
    ) -> FakeExport:
        if self.delay:
            await asyncio.sleep(self.delay)
        if receiver == self.fail_for:
            raise RuntimeError(f"no route to {receiver} for {local}")
        if local in self.missing:  # as the proxy's subscription would: naming local labels
            raise UnknownLabelError(local, sorted(self.missing))
        export = FakeExport(local, semantic, receiver, policy, history)
        self.started.append(export)
        return export

    def stop(self, export: FakeExport, *, why: str | None = None) -> None:
        export.stopped, export.why = True, why

    @property
    def running(self) -> list[FakeExport]:
        return [e for e in self.started if not e.stopped]


class Silent(Agent):
    """Lists a federation service but never answers: a platform too busy to reply."""

    def __init__(self) -> None:
        super().__init__("federation")
        self.got = asyncio.Event()
        self.performatives: list[P] = []

    async def setup(self) -> None:
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
    async def _swallow(self, message: Any) -> None:
        self.performatives.append(message.performative)
        self.got.set()


# -- the world ---------------------------------------------------------------------------------


@dataclass
class Node:
    platform: AgentPlatform
    transport: MemoryTransport
    dk: DyKnowInstance
    fed: FederationAgent
    exporter: FakeExporter
    sources: dict[str, Source]  # by semantic label

    def push(self, semantic: str, value: Any, seconds_ago: float) -> None:
        self.sources[semantic].push(value, valid_time=T0 - round(seconds_ago * NS_PER_S))


@dataclass
class World:
    nodes: dict[str, Node]
    clock: ManualClock
    silent: dict[str, Silent]

    def __getitem__(self, name: str) -> Node:
        return self.nodes[name]


@contextlib.asynccontextmanager
async def world(*, silent: tuple[str, ...] = (), **options: Any) -> AsyncIterator[World]:
    """uav-a, uav-b and operator (plus ``silent`` ones), all members before the test runs.

    Each agrees to receive the streams another platform asks for it (``to-units`` naming
    a third platform), unless ``consent`` says otherwise: the consent itself is tested on
    spawned platforms in tests/test_member_authz.py.
    """
    options.setdefault("consent", lambda requester, provider, labels: None)
    names = list(TABLES)
    keys = {n: KeyPair.generate(n) for n in [*names, *silent]}
    hub = MemoryHub()
    clock = ManualClock(T0)
    async with asyncio.timeout(10), contextlib.AsyncExitStack() as stack:

        async def open_platform(name: str) -> tuple[AgentPlatform, MemoryTransport]:
            trust = TrustStore(FED, {n: k.public_key for n, k in keys.items()})
            t = await stack.enter_async_context(hub.transport())
            channel = InterfaceAgent(keys[name], trust, audit_interval=0.02)
            p = await stack.enter_async_context(
                AgentPlatform(name, t, federation=FED, channel=channel)
            )
            return p, t

        nodes: dict[str, Node] = {}
        streams = {}
        for name in names:
            dk = await stack.enter_async_context(DyKnowInstance(name, clock=clock))
            sources = {s: dk.add_source(local) for s, local in TABLES[name].items()}
            p, t = await open_platform(name)
            exporter = FakeExporter()
            fed = await p.add(
                FederationAgent(
                    dk,
                    FakeTranslator(TABLES[name]),
                    exporter=exporter,
                    search=FakeSearch(),
                    **options,
                )
            )
            streams[name] = fed.membership()
            nodes[name] = Node(p, t, dk, fed, exporter, sources)
        quiet = {}
        for name in silent:
            p, _ = await open_platform(name)
            quiet[name] = await p.add(Silent())
        members = sorted([*names, *silent])
        for name, stream in streams.items():  # each learns of the later ones by events
            async with stream:
                while nodes[name].fed.members != members:
                    await stream.get(timeout=WAIT)
        yield World(nodes, clock, quiet)
    assert asyncio.all_tasks() == {asyncio.current_task()}


async def refusal(call: Awaitable[Any]) -> str:
    """The reason a refused call carries."""
    with pytest.raises(Refused) as info:
        await call
    assert info.value.message is not None
    reason = info.value.message.content
    assert isinstance(reason, str)
    return reason


def no_local_labels(content: Any, platform: str) -> bool:
    """Whether none of ``platform``'s local labels appears anywhere in ``content``."""
    text = orjson.dumps(content).decode()
    return not any(local in text for local in TABLES[platform].values())


async def next_event(stream: Any, want: Any) -> Any:
    """Read ``stream`` (bounded) until an item equal to ``want``."""
    async with asyncio.timeout(WAIT):
        while (item := await stream.get()) != want:
            pass
    return item


# -- create-stream and cancel -------------------------------------------------------------------


async def test_create_stream_is_agreed_and_exported_to_each_receiver() -> None:
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        answer = await request(
            b.fed,
            "federation@uav-a",
            {
                "action": "create-stream",
                "semantic-labels": ["car5-state"],  # the paper's spelling
                "sample-period": 0.5,
                "max-delay": 1,
                "from": -10,
                "relative": True,
                "to-units": ["uav-b"],
            },
            ontology=ONTOLOGY,
            timeout=WAIT,
        )
        assert answer == {"id": answer["id"], "labels": ["car5-state"], "to-units": ["uav-b"]}
        assert no_local_labels(answer, "uav-a")
        # to a third platform: it agrees (world's consent), after uav-b confirms it asked
        await b.fed.create_stream(
            "uav-a",
            ["car5-state"],
            to_units=["operator"],
            sample_period=0.5,
            max_delay=1,
            start=-10,
            relative=True,
        )
        started = a.exporter.started
        assert [(e.local, e.semantic, e.receiver) for e in started] == [
            ("a/cars/car5/state", "car5-state", "uav-b"),
            ("a/cars/car5/state", "car5-state", "operator"),
        ]
        policy = started[0].policy
        assert (policy.sample_period, policy.max_delay) == (0.5, 1.0)
        assert policy.start == T0 - 10 * NS_PER_S and policy.end is None
        record = a.fed.exports[answer["id"]]
        assert record.requester == "federation@uav-b"
        assert a.fed.export_count == 2
        # It came through uav-a's Interface Agent, authenticated and audited.
        assert isinstance(a.platform.channel, InterfaceAgent)
        assert any(
            r["sender"] == "federation@uav-b" and r["verdict"] == "accepted"
            for r in a.platform.channel.audit.records
        )
        # The Python helper asks the same, to the requester by default.
        export_id = await b.fed.create_stream("uav-a", ["heli-altitude"], sample_period=2)
        assert started[-1].receiver == "uav-b" and started[-1].policy.sample_period == 2
        assert export_id in a.fed.exports
        assert [e.history for e in started] == [0, 0, 0]
        # history: the exporter keeps the last N samples to resend what a partition lost
        await b.fed.create_stream("uav-a", ["heli-max-speed"], history=50)
        assert (started[-1].semantic, started[-1].history) == ("heli-max-speed", 50)


async def test_a_reloaded_sharing_ends_the_exports_it_no_longer_allows() -> None:
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        kept = await b.fed.create_stream("uav-a", ["heli-altitude"])
        gone = await b.fed.create_stream("uav-a", ["car5-state"], to_units=["uav-b", "operator"])
        rule = SharingRule(name="cars", labels=["car*"], stream=["operator"])
        a.fed.sharing = Sharing(SharingSettings(rules=[rule]))
        ended = await a.fed.end_unshared("reloaded")
        # its requester may no longer stream it: every receiver's export of it ends
        assert [(i, s, r) for i, s, r, _ in ended] == [
            (gone, "car5-state", "uav-b"),
            (gone, "car5-state", "operator"),
        ]
        assert all("sharing rule 'cars'" in reason for *_, reason in ended)
        assert set(a.fed.exports) == {kept}
        stopped = [e for e in a.exporter.started if e.stopped]
        assert [e.semantic for e in stopped] == ["car5-state", "car5-state"]
        # told the fact, short, not the rule's platforms nor the reload's file
        assert all(e.why == "the provider's sharing policy no longer allows it" for e in stopped)
        assert [e.semantic for e in a.exporter.running] == ["heli-altitude"]
        assert await a.fed.end_unshared("reloaded") == []


async def test_a_reload_ending_an_export_tells_the_receiver_in_a_marker_it_accepts() -> None:
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        await b.fed.create_stream("uav-a", ["car5-state"])
        # a rule naming 40 platforms: its refusal lists them, over a marker's 1024 characters
        many = [f"platform-with-a-long-name-{i:02d}" for i in range(40)]
        rule = SharingRule(name="cars", labels=["car*"], stream=many)
        a.fed.sharing = Sharing(SharingSettings(rules=[rule]))
        ended = await a.fed.end_unshared("the sharing policy was reloaded from /etc/node.toml")
        assert len(ended) == 1 and len(ended[0][3]) > 1024  # the refusal, kept for the audit
        (stopped,) = [e for e in a.exporter.started if e.stopped]
        assert stopped.why is not None and len(stopped.why) <= 200
        assert "/etc/node.toml" not in stopped.why and "platform-with" not in stopped.why
        marker = read_batch(pack_batch("car5-state", [], 0, ended=stopped.why))
        assert marker.ended == stopped.why  # the receiver reads it: its import ends


async def test_a_reload_ends_every_refused_export_before_telling_any_receiver() -> None:
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        for label in ("car5-state", "heli-altitude", "heli-max-speed"):
            await b.fed.create_stream("uav-a", [label])
        events: list[tuple[str, str]] = []

        async def stop(export: FakeExport, *, why: str | None = None) -> None:
            export.stopped, export.why = True, why  # it sends no more from here
            events.append(("ended", export.semantic))
            await asyncio.sleep(0.05)  # its end marker on the wire
            events.append(("told", export.semantic))

        a.exporter.stop = stop  # type: ignore[method-assign]
        a.fed.sharing = Sharing(SharingSettings(default="none"))
        async with asyncio.timeout(WAIT):
            ended = await a.fed.end_unshared("reloaded")
        assert len(ended) == 3 and a.fed.exports == {}
        assert [e for e, _ in events] == ["ended"] * 3 + ["told"] * 3, events


async def test_a_create_stream_started_across_a_reload_is_checked_by_the_new_policy() -> None:
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        starting = asyncio.Event()
        start = a.exporter.start_exporting

        async def slow(*args: Any, **options: Any) -> FakeExport:
            starting.set()  # checked by the old policy, starting
            await asyncio.sleep(0.3)
            return await start(*args, **options)

        a.exporter.start_exporting = slow  # type: ignore[method-assign]
        asked = asyncio.create_task(b.fed.create_stream("uav-a", ["car5-state"]))
        async with asyncio.timeout(WAIT):
            await starting.wait()
        a.fed.sharing = Sharing(SharingSettings(default="none"))
        assert await a.fed.end_unshared("reloaded") == []  # not running yet
        reason = await refusal(asked)
        assert 'sharing.default is "none"' in reason, reason
        assert a.exporter.running == [] and a.fed.exports == {}


async def test_a_reload_while_a_create_stream_starts_stops_it_before_the_next_label() -> None:
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        starting = asyncio.Event()
        start = a.exporter.start_exporting

        async def slow(*args: Any, **options: Any) -> FakeExport:
            export = await start(*args, **options)  # this one runs: it may send
            starting.set()
            await asyncio.sleep(0.3)
            return export

        a.exporter.start_exporting = slow  # type: ignore[method-assign]
        asked = asyncio.create_task(b.fed.create_stream("uav-a", ["car5-state", "heli-altitude"]))
        async with asyncio.timeout(WAIT):
            await starting.wait()
        a.fed.sharing = Sharing(SharingSettings(default="none"))
        reason = await refusal(asked)
        assert 'sharing.default is "none"' in reason, reason
        # the next label never started; the one running stopped, its receiver told
        assert [e.semantic for e in a.exporter.started] == ["car5-state"]
        (first,) = a.exporter.started
        assert first.stopped and first.why == "the provider's sharing policy no longer allows it"
        assert a.fed.exports == {}


async def test_concurrent_create_streams_of_one_requester_are_all_agreed() -> None:
    # regression: the per-requester reservations of two requests in flight at once were
    # released twice, and the second request failed
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        labels = ["car5-state", "heli-altitude", "heli-max-speed"]
        a.exporter.delay = 0.05
        ids = await asyncio.gather(*(b.fed.create_stream("uav-a", [s]) for s in labels))
        assert len(set(ids)) == 3 and sorted(e.semantic for e in a.exporter.running) == labels
        assert a.fed._reserved_by == {} and a.fed._history_reserved_by == {}


async def test_create_stream_refusals_name_the_reason() -> None:
    async with world(max_exports=2) as w:
        a, b = w["uav-a"], w["uav-b"]

        def ask(**content: Any) -> Awaitable[Any]:
            return b.fed.request_from("uav-a", {"action": "create-stream", **content}, timeout=WAIT)

        reason = await refusal(ask(labels=["car5-state", "car9-state"]))
        assert reason == "semantic label 'car9-state' has no mapping on this platform"
        assert "to itself" in await refusal(ask(labels=["car5-state"], **{"to-units": ["uav-a"]}))
        # no presence at all: not told to ask again
        assert await refusal(ask(labels=["car5-state"], **{"to-units": ["nowhere"]})) == (
            "unknown receiver nowhere: not in the federation"
        )
        assert a.fed.refusals.get("unlisted-receiver") == 1, a.fed.refusals
        assert "sample-period" in await refusal(ask(labels=["car5-state"], **{"sample-period": -1}))
        assert "start" in await refusal(ask(labels=["car5-state"], **{"from": 20, "to": 10}))
        assert "history" in await refusal(ask(labels=["car5-state"], history=-1))
        assert "unknown action" in await refusal(b.fed.request_from("uav-a", {"action": "fly"}))
        assert a.exporter.started == []

        # The limit counts a label to a receiver: 2 fit, the third does not.
        first = await ask(labels=["car5-state", "heli-altitude"])
        reason = await refusal(ask(labels=["heli-max-speed"]))
        assert reason.startswith("too many exports (limit 2")
        assert len(a.exporter.running) == 2
        # The same label to the same receiver twice: the first export stays the only one.
        await b.fed.cancel_stream("uav-a", first["id"])
        await ask(labels=["car5-state"])
        assert "already goes to uav-b" in await refusal(ask(labels=["car5-state"]))

    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        # Mapped, but no stream behind it (the exporter cannot subscribe): refused, and
        # the core's message, which lists local labels, stays here.
        a.exporter.missing = {"a/cars/car5/state"}
        reason = await refusal(b.fed.create_stream("uav-a", ["car5-state"]))
        assert reason == "label 'car5-state': no stream for it here"

    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        a.exporter.fail_for = "operator"
        with pytest.raises(Failed) as failed:
            await b.fed.create_stream("uav-a", ["car5-state"], to_units=["uav-b", "operator"])
        assert failed.value.message is not None
        reason = str(failed.value.message.content)
        assert "car5-state" in reason and "operator" in reason
        assert no_local_labels(reason, "uav-a")
        # What had started (to uav-b) was stopped again: nothing half-done is left.
        assert len(a.exporter.started) == 1 and a.exporter.running == []
        assert a.fed.exports == {}


async def test_a_members_refusals_past_its_budget_are_neither_logged_nor_recorded_each(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A refusal by a limit (here: a receiver not in the federation), asked again and again:
    each counted; a log line and a record each only within the asking platform's budget,
    the rest summed up (`count`) and not logged, however many a member asks."""
    n = REFUSALS_ONE_BY_ONE + 15
    told = "unknown receiver nowhere: not in the federation"
    content = {"action": "create-stream", "labels": ["car5-state"], "to-units": ["nowhere"]}
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        loop = asyncio.get_running_loop()
        with caplog.at_level(logging.INFO, logger="federation._service"):
            t0 = loop.time()
            reasons = await asyncio.gather(
                *[refusal(b.fed.request_from("uav-a", content, timeout=WAIT)) for _ in range(n)]
            )
            elapsed = loop.time() - t0
        assert reasons == [told] * n
        assert a.fed.refusals == {"unlisted-receiver": n}

        def recs() -> list[dict[str, Any]]:
            return [
                r
                for r in a.platform.channel.audit.records
                if r.get("stage") == "federation" and r.get("code") == "unlisted-receiver"
            ]

        await until(lambda: sum(r.get("count") or 1 for r in recs()) == n, "all audited", 5)
        one_by_one = [r for r in recs() if r.get("count") is None]
        intervals = int(elapsed // REFUSAL_AUDIT_INTERVAL) + 1
        assert REFUSALS_ONE_BY_ONE <= len(one_by_one) <= REFUSALS_ONE_BY_ONE * intervals
        assert all(r["reason"] == f"unlisted-receiver: {told}" for r in one_by_one)
        logged = [
            r
            for r in caplog.records
            if r.name == "federation._service" and "refused federation@uav-b" in r.getMessage()
        ]
        assert len(logged) == len(one_by_one)  # a line for each record one by one only
        if n > REFUSALS_ONE_BY_ONE * intervals:
            assert any(r.get("count") for r in recs())


async def test_cancel_stream_by_action_and_by_fipa_cancel() -> None:
    async with world() as w:
        a, b, op = w["uav-a"], w["uav-b"], w["operator"]
        export_id = await b.fed.create_stream("uav-a", ["car5-state"])
        # Neither its requester's platform nor a receiver: may not cancel.
        reason = await refusal(op.fed.cancel_stream("uav-a", export_id))
        assert "may not cancel" in reason
        await b.fed.cancel_stream("uav-a", export_id)
        assert a.exporter.running == [] and a.fed.exports == {}
        assert "no export" in await refusal(b.fed.cancel_stream("uav-a", export_id))

        # FIPA cancel in the create-stream's conversation stops it too.
        conversation_id = new_id("c")
        create = b.fed.message(
            P.REQUEST,
            "federation@uav-a",
            {"action": "create-stream", "labels": ["heli-altitude"]},
            protocol=FIPA_REQUEST,
            ontology=ONTOLOGY,
            conversation_id=conversation_id,
        )
        agreed = await b.fed.ask(create, timeout=WAIT)
        assert agreed.performative is P.INFORM
        assert len(a.exporter.running) == 1
        cancel = b.fed.message(
            P.CANCEL,
            "federation@uav-a",
            None,
            protocol=FIPA_REQUEST,
            ontology=ONTOLOGY,
            conversation_id=conversation_id,
        )
        done = await b.fed.ask(cancel, timeout=WAIT)
        assert done.performative is P.INFORM
        assert done.content == {"cancelled": agreed.content["id"]}  # type: ignore[index]
        assert a.exporter.running == [] and a.fed.exports == {}


async def test_one_senders_early_cancels_forget_only_its_own() -> None:
    # regression: the early cancels kept were one FIFO for all senders, so a member sending
    # fresh conversations pushed out another's
    async with world() as w:
        a, b, op = w["uav-a"], w["uav-b"], w["operator"]

        async def cancel(fed: FederationAgent, conversation_id: str) -> None:
            message = fed.message(
                P.CANCEL,
                "federation@uav-a",
                None,
                protocol=FIPA_REQUEST,
                ontology=ONTOLOGY,
                conversation_id=conversation_id,
            )
            assert (await fed.ask(message, timeout=WAIT)).performative is P.INFORM

        await cancel(op.fed, "c-op")
        for i in range(20):
            await cancel(b.fed, f"c-b{i}")
        kept = list(a.fed._cancelled_early)
        assert (op.fed.aid, "c-op") in kept
        assert [c for s, c in kept if s == b.fed.aid] == [f"c-b{i}" for i in range(4, 20)]


# -- queries ----------------------------------------------------------------------------------


async def test_get_trajectory_relative_and_value_at_answer_in_semantic_labels() -> None:
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        for i in range(30):  # car5's state every 10 s, from 300 s ago to 10 s ago
            a.push("car5-state", {"pos": (float(i), 2.0 * i)}, seconds_ago=300 - 10 * i)
        trajectory = await b.fed.request_from(
            "uav-a",
            {"action": "get-trajectory", "labels": ["car5-state"], "from": -120, "relative": True},
        )
        assert list(trajectory) == ["car5-state"]
        samples = trajectory["car5-state"]["samples"]
        assert [row[1] for row in samples] == [880.0 + 10 * i for i in range(12)]
        assert samples[0][0] == {"pos": [18.0, 36.0]}
        assert trajectory["car5-state"]["query_time"] == 1000.0
        assert no_local_labels(trajectory, "uav-a")

        at = await b.fed.request_from(
            "uav-a",
            {"action": "get-value-at", "labels": ["car5-state"], "t": -15, "relative": True},
        )
        # The fluent generator's value at 985 s: the most recent sample (valid at 980 s).
        assert [row[:2] for row in at["car5-state"]["samples"]] == [[{"pos": [28.0, 56.0]}, 985.0]]
        latest = await query_ref(
            b.fed,
            "federation@uav-a",
            {"action": "get-latest", "labels": ["car5-state"], "to-units": ["uav-b"]},
            ontology=ONTOLOGY,
        )
        assert latest["car5-state"]["samples"][0][0] == {"pos": [29.0, 58.0]}  # type: ignore[index]

        # Answers go to the asker; an unknown label refuses the whole query.
        reason = await refusal(
            b.fed.request_from(
                "uav-a",
                {"action": "get-latest", "labels": ["car5-state"], "to-units": ["operator"]},
            )
        )
        assert "to-units" in reason
        reason = await refusal(
            b.fed.request_from("uav-a", {"action": "get-latest", "labels": ["car5-state", "x9"]})
        )
        assert "'x9'" in reason
        # Known here but no stream behind it: refused without the local label.
        a.dk.remove_stream("a/state/altitude")
        reason = await refusal(
            b.fed.request_from("uav-a", {"action": "get-latest", "labels": ["heli-altitude"]})
        )
        assert "heli-altitude" in reason and no_local_labels(reason, "uav-a")
        # Actions are asked for with FIPA-Request, not FIPA-Query.
        reason = await refusal(
            query_ref(
                b.fed,
                "federation@uav-a",
                {"action": "create-stream", "labels": ["car5-state"]},
                ontology=ONTOLOGY,
            )
        )
        assert "FIPA-Request" in reason


async def test_get_latest_across_platforms() -> None:
    async with world() as w:
        w["uav-a"].push("heli-altitude", 120.0, seconds_ago=2)
        w["uav-b"].push("heli-altitude", 80.0, seconds_ago=1)
        op = w["operator"].fed
        content = {"action": "get-latest", "labels": ["heli-altitude"]}
        from_a, from_b = await asyncio.gather(
            op.request_from("uav-a", content), op.request_from("uav-b", content)
        )
        assert from_a["heli-altitude"]["samples"][0][:2] == [120.0, 998.0]
        assert from_b["heli-altitude"]["samples"][0][:2] == [80.0, 999.0]
        assert await op.request_from("operator", {"action": "list-labels"}) == {
            "labels": ["picture"]
        }


_HOSTILE_LATEST: list[Any] = [
    {"action": "get-latest", "labels": ["heli-altitude", "car5-state"]},
    {"labels": ["car5-state", "heli-altitude", "car5-state"], "action": "get-latest"},
    {"action": "get-latest", "labels": ["secret-state"]},  # a sharing rule refuses it
    {"action": "get-latest", "labels": ["heli-altitude", "secret-state", "x9"]},
    {"action": "get-latest", "labels": ["x9", "secret-state"]},
    {"action": "get-latest", "labels": ["heli-max-speed"]},  # no sample yet
    {"action": "get-latest", "labels": ["gone-state"]},  # mapped, no stream behind it
    {"action": "get-latest", "semantic-labels": ["car5-state"]},
    {"action": "get-latest", "labels": ["car5-state"], "relative": True},
    {"action": "get-latest", "labels": ["car5-state"], "to-units": ["uav-b"]},
    {"action": "get-latest", "labels": ["car5-state"], "to-units": ["operator"]},
    {"action": "get-latest", "labels": ["car5-state"], "extra": 1},
    {"action": "get-latest", "labels": []},
    {"action": "get-latest", "labels": [""]},
    {"action": "get-latest", "labels": ["x" * 200]},
    {"action": "get-latest", "labels": ["x" * 201]},
    {"action": "get-latest", "labels": ["car5-state"] * 64},
    {"action": "get-latest", "labels": ["car5-state"] * 65},
    {"action": "get-latest", "labels": ["car5-state", 5]},
    {"action": "get-latest", "labels": "car5-state"},
    {"action": "get-latest", "labels": None},
    {"action": "get-latest"},
    {"action": "get-value-at", "labels": ["car5-state"]},
    {"action": "list-labels", "labels": ["car5-state"]},
    {"action": 1, "labels": ["car5-state"]},
    {"action": "get-latest ", "labels": ["car5-state"]},
    ["get-latest", ["car5-state"]],
    None,
]


async def _asked_hostile(fed: FederationAgent) -> list[Any]:
    """uav-a's answer to each of `_HOSTILE_LATEST`, asked by request and by query-ref."""
    got: list[Any] = []
    for content in _HOSTILE_LATEST:
        for ask in (fed.request_from, _query_ref_of(fed)):
            try:
                got.append(("inform", await ask("uav-a", content)))
            except Refused as exc:
                assert exc.message is not None
                got.append(("refuse", exc.message.content))
    return got


async def test_a_plain_get_latest_is_decided_as_its_model_decides(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The quick path of a plain get-latest: the same answers, refusals and counts as without."""
    from federation import _service

    rule = SharingRule(name="private", labels=["secret-*"], query=["operator"])
    sharing = Sharing(SharingSettings(rules=[rule]))
    tables = {**TABLES["uav-a"], "secret-state": "a/secret", "gone-state": "a/gone"}

    at_once: list[int] = []

    async def outcomes(answer_at_once: bool = True) -> tuple[list[Any], dict[str, int]]:
        async with world(sharing=sharing) as w:
            a, b = w["uav-a"], w["uav-b"]
            a.fed.translator = FakeTranslator(tables)
            a.fed._at_once = answer_at_once
            a.dk.add_source("a/secret").push(7, valid_time=T0 - NS_PER_S)
            a.push("car5-state", {"pos": [1.0, 2.0]}, seconds_ago=3)
            a.push("heli-altitude", 120.0, seconds_ago=2)
            got = await _asked_hostile(b.fed), dict(a.fed.refusals)
            at_once.append(a.fed.stats.answered_at_once)
            return got

    quick = await outcomes()
    assert sum(1 for kind, _ in quick[0] if kind == "inform") >= 8
    assert quick[1].get("sharing-rule", 0) == 6
    # every inform answering a plain get-latest was answered as it came (`answer_at_once`,
    # each content asked twice: by request and by query-ref); the refusals went through
    # the handlers, which counted them above
    asked = [content for content in _HOSTILE_LATEST for _ in range(2)]
    plain = [
        content
        for content, (kind, _) in zip(asked, quick[0], strict=True)
        if kind == "inform" and latest_labels(content) is not None
    ]
    assert len(plain) >= 6
    assert at_once == [len(plain)]
    # the same without answering at once, and without the quick path at all
    assert await outcomes(answer_at_once=False) == quick
    monkeypatch.setattr(_service, "latest_labels", lambda content: None)
    assert await outcomes() == quick
    assert at_once == [len(plain), 0, 0]


# uav-a's labels as the ontology translates them: a pattern, fixed labels, one unmapped
_VOCABULARY = Vocabulary(
    ["heli-max-speed", "heli-altitude", "secret-state", "gone-state", "x9", "{object}-state"]
)
_MAPPING = {
    "heli-max-speed": "a/limits/max_speed",
    "heli-altitude": "a/state/altitude",
    "secret-state": "a/secret",
    "gone-state": "a/gone",
    "{object}-state": "a/cars/{object}/state",
}


class _TranslatedAfresh(PlatformLabels):
    """`PlatformLabels` as another translator: the provider keeps none of its translations."""


async def test_a_kept_get_latest_translation_decides_as_a_fresh_one() -> None:
    """The provider keeps the translation of the labels a get-latest asks (`PlatformLabels`):
    the same answers, refusals and counts as translating each time, asked twice over."""
    rule = SharingRule(name="private", labels=["secret-*"], query=["operator"])
    sharing = Sharing(SharingSettings(rules=[rule]))

    async def outcomes(
        translator: type[PlatformLabels],
    ) -> tuple[list[Any], dict[str, int], int]:
        async with world(sharing=sharing) as w:
            a, b = w["uav-a"], w["uav-b"]
            a.fed.translator = translator(LabelMapping(_VOCABULARY, _MAPPING), a.dk)
            a.dk.add_source("a/secret").push(7, valid_time=T0 - NS_PER_S)
            a.push("car5-state", {"pos": [1.0, 2.0]}, seconds_ago=3)
            a.push("heli-altitude", 120.0, seconds_ago=2)
            got = await _asked_hostile(b.fed) + await _asked_hostile(b.fed)
            return got, dict(a.fed.refusals), len(a.fed._resolved)

    kept = await outcomes(PlatformLabels)
    assert kept[2] > 0  # the kept translations answered the second round
    assert sum(1 for kind, _ in kept[0] if kind == "inform") >= 16
    assert kept[1].get("sharing-rule", 0) == 12
    afresh = await outcomes(_TranslatedAfresh)
    assert afresh[2] == 0
    assert afresh[:2] == kept[:2]


async def test_a_kept_get_latest_translation_follows_mapping_sharing_and_streams() -> None:
    """What the provider keeps of a get-latest is dropped as the mapping, the translator,
    the sharing rules or the streams change: the next answer is the new one."""
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        a.fed.translator = labels = PlatformLabels(LabelMapping(_VOCABULARY, _MAPPING), a.dk)
        a.push("heli-altitude", 120.0, seconds_ago=2)
        a.push("heli-max-speed", 25.0, seconds_ago=9)
        a.push("car5-state", "car5 here", seconds_ago=1)
        content = {"action": "get-latest", "labels": ["heli-altitude", "car5-state"]}

        async def values() -> list[Any]:
            answer = await b.fed.request_from("uav-a", content)
            return [answer[s]["samples"][0][0] for s in content["labels"]]

        assert await values() == await values() == [120.0, "car5 here"]
        # another mapping in the same translator: heli-altitude is the max-speed stream
        swapped = {"heli-altitude": "a/limits/max_speed", "heli-max-speed": "a/state/altitude"}
        labels.mapping = LabelMapping(_VOCABULARY, {**_MAPPING, **swapped})
        assert await values() == [25.0, "car5 here"]
        # another translator
        a.fed.translator = PlatformLabels(LabelMapping(_VOCABULARY, _MAPPING), a.dk)
        assert await values() == [120.0, "car5 here"]
        # a sharing rule that refuses uav-b, then none
        rule = SharingRule(name="mine", labels=["car*"], query=["operator"])
        a.fed.sharing = Sharing(SharingSettings(rules=[rule]))
        assert "sharing rule 'mine'" in await refusal(b.fed.request_from("uav-a", content))
        assert a.fed.refusals == {"sharing-rule": 1}
        a.fed.sharing = Sharing()
        assert await values() == [120.0, "car5 here"]
        # the stream behind a label gone, then back
        a.dk.remove_stream("a/cars/car5/state")
        reason = await refusal(b.fed.request_from("uav-a", content))
        assert reason == "label 'car5-state': no stream for it here"
        a.dk.add_source("a/cars/car5/state", name="car5 again").push("car5 back", valid_time=T0)
        assert await values() == [120.0, "car5 back"]
        # another translator kind: asked each time
        a.fed.translator = FakeTranslator({"heli-altitude": "a/limits/max_speed"})
        assert "car5-state" in await refusal(b.fed.request_from("uav-a", content))
        content["labels"] = ["heli-altitude"]
        assert await values() == [25.0]


async def test_the_kept_get_latest_translations_are_bounded() -> None:
    """Members asking ever new lists of valid labels (a pattern's) keep a bounded number."""
    from federation._service import _MAX_RESOLVED

    async with world() as w:
        a = w["uav-a"]
        a.fed.translator = PlatformLabels(LabelMapping(_VOCABULARY, _MAPPING), a.dk)
        a.push("heli-altitude", 120.0, seconds_ago=2)
        asks = _MAX_RESOLVED // 4 + 10  # 4 labels each: past the bound
        for i in range(asks):
            labels = ["heli-altitude", f"obj{i}-state", f"obj{i + 1}-state", "heli-altitude"]
            with pytest.raises(ContentError, match=f"obj{i}-state.: no stream for it here"):
                a.fed._latest_reply(labels, "uav-b")
            kept = sum(map(len, a.fed._resolved))
            assert kept == a.fed._resolved_labels <= _MAX_RESOLVED
        assert 0 < len(a.fed._resolved) < asks  # dropped once, kept again since
        answer = a.fed._latest_reply(["heli-altitude"], "uav-b").value
        assert answer["heli-altitude"]["samples"][0][0] == 120.0


def _query_ref_of(fed: FederationAgent) -> Any:
    async def ask(platform: str, content: Any) -> Any:
        return await query_ref(fed, f"federation@{platform}", content, ontology=ONTOLOGY)

    return ask


@settings(max_examples=500, deadline=None)
@given(
    st.dictionaries(
        st.sampled_from(["action", "labels", "semantic-labels", "relative", "to-units"]),
        st.sampled_from(["get-latest", "get-latest\n", "get-value-at", 1, None, True])
        | st.lists(
            st.text(max_size=3)
            | st.text(min_size=199, max_size=201)
            | st.integers()
            | st.none()
            | st.binary(max_size=2),
            max_size=66,
        ),
    )
    | st.fixed_dictionaries(
        {
            "action": st.just("get-latest"),
            "labels": st.lists(
                st.text(max_size=4) | st.text(min_size=198, max_size=202), max_size=66
            )
            | st.builds(lambda n: ["s"] * n, st.integers(0, 70)),
        }
    )
)
def test_the_quick_get_latest_labels_are_those_of_the_model(content: dict[str, Any]) -> None:
    """latest_labels: the labels parse_request's GetLatest has, on the exact shape, else None."""
    try:
        parsed: Any = parse_request(content)
    except ContentError:
        parsed = None
    quick = latest_labels(content)
    if quick is not None:
        assert isinstance(parsed, GetLatest)
        assert parsed.labels == quick and parsed.to_units is None
    exact = content.keys() == {"action", "labels"} and isinstance(content["labels"], list)
    if exact and all(type(s) is str for s in content["labels"]):
        # on the exact shape, with labels of the exact type, it decides as the model does
        assert (quick is not None) == isinstance(parsed, GetLatest)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.builds(
            lambda labels, query: SharingRule(labels=labels, query=query),
            st.lists(st.sampled_from(["car*", "heli-?ltitude", "*", "x[0-9]"]), min_size=1),
            st.lists(st.sampled_from(["uav-*", "operator", "*"]), max_size=2),
        ),
        max_size=3,
    ),
    st.sampled_from(["members", "none"]),
    st.lists(st.sampled_from(["car5", "heli-altitude", "x1", "y"]), max_size=4),
    st.sampled_from(["uav-b", "operator"]),
)
def test_check_all_is_the_first_refusal_of_check(
    rules: list[SharingRule], default: Any, labels: list[str], platform: str
) -> None:
    """Sharing.check_all: what `check` of each label says first, with or without rules."""
    sharing = Sharing(SharingSettings(rules=rules, default=default))
    want = next((r for s in labels if (r := sharing.check("query", s, platform)) is not None), None)
    assert sharing.check_all("query", labels, platform) == want


def test_check_all_asks_a_subclass_s_own_check() -> None:
    """A `Sharing` that decides otherwise (its own `check`) is asked, default table or not."""

    class NoCars(Sharing):
        def check(self, action: Any, label: str, platform: str) -> str | None:
            return "no cars" if label.startswith("car") else super().check(action, label, platform)

    assert NoCars().check_all("query", ["heli-altitude", "car5"], "uav-b") == "no cars"
    assert NoCars().check_all("query", ["heli-altitude"], "uav-b") is None


# -- global requests ------------------------------------------------------------------------------


async def test_global_request_names_the_silent_platform() -> None:
    async with world(silent=("uav-c",)) as w:
        b = w["uav-b"]
        b.push("heli-max-speed", 25.0, seconds_ago=30)
        b.push("heli-altitude", 60.0, seconds_ago=1)
        a = w["uav-a"].fed
        result = await a.global_request(
            {"action": "get-latest", "labels": ["heli-max-speed", "heli-altitude"]},
            deadline=0.3,
        )
        assert result.asked == ["operator", "uav-b", "uav-c"]
        assert list(result.answers) == ["uav-b"]
        assert result.chosen == "uav-b" and result.value == result.answers["uav-b"]
        assert result.value["heli-max-speed"]["samples"][0][0] == 25.0  # type: ignore[index]
        assert result.value["heli-altitude"]["samples"][0][0] == 60.0  # type: ignore[index]
        assert list(result.refused) == ["operator"]
        assert "heli-max-speed" in result.refused["operator"]
        assert result.no_answer == ["uav-c"]
        assert w.silent["uav-c"].got.is_set()  # it was asked; it did not answer
        # a reading action is asked as a query: answered without a task per request
        assert w.silent["uav-c"].performatives == [P.QUERY_REF]


async def test_global_request_selects_newest_or_fuses() -> None:
    async with world() as w:
        w["uav-a"].push("heli-altitude", 120.0, seconds_ago=5)
        w["uav-b"].push("heli-altitude", 80.0, seconds_ago=1)
        op = w["operator"].fed
        content = {"action": "get-latest", "labels": ["heli-altitude"]}
        loop = asyncio.get_running_loop()
        started = loop.time()
        # a deadline far off: back well before it is no wait for it, however busy the machine
        newest = await op.global_request(content, deadline=10 * WAIT, select="newest")
        assert loop.time() - started < 5 * WAIT  # everyone answered: no wait for the deadline
        assert sorted(newest.answers) == ["uav-a", "uav-b"]
        assert newest.chosen == "uav-b"
        assert newest.value["heli-altitude"]["samples"][0][0] == 80.0  # type: ignore[index]
        assert newest.no_answer == [] and newest.refused == {}

        def highest(answers: dict[str, Any]) -> float:
            return max(a["heli-altitude"]["samples"][-1][0] for a in answers.values())

        fused = await op.global_request(content, deadline=WAIT, select=highest)
        assert fused.value == 120.0 and fused.chosen is None

        # Asking ourselves too: the operator has no altitude and says so.
        first = await op.global_request(content, deadline=WAIT, include_self=True)
        assert first.asked == ["operator", "uav-a", "uav-b"]
        assert first.chosen in ("uav-a", "uav-b")
        assert "heli-altitude" in first.refused["operator"]

        # Local agents may ask the service for a global request; other platforms may not.
        asker = await w["operator"].platform.add(Agent("asker"))
        on_behalf = await request(
            asker,
            "federation@operator",
            {"action": "global-request", "request": content, "deadline": 1, "select": "newest"},
            ontology=ONTOLOGY,
        )
        assert on_behalf["chosen"] == "uav-b"  # type: ignore[index]
        assert on_behalf["no-answer"] == []  # type: ignore[index]
        assert on_behalf["unlisted"] == []  # type: ignore[index]
        reason = await refusal(
            w["uav-b"].fed.request_from(
                "operator", {"action": "global-request", "request": content, "deadline": 1}
            )
        )
        assert "this platform only" in reason


async def altitudes_and_operator_sessions(w: dict[str, Any], *agreed: str) -> InterfaceAgent:
    """Both UAVs' altitudes pushed (uav-b's newer); the operator's channel, sessions agreed."""
    w["uav-a"].push("heli-altitude", 120.0, seconds_ago=5)
    w["uav-b"].push("heli-altitude", 80.0, seconds_ago=1)
    channel = w["operator"].platform.channel
    assert isinstance(channel, InterfaceAgent)
    for platform in agreed:
        await channel.agree(platform)
    return channel


async def test_global_request_sends_in_turn_or_in_a_task_where_it_must_agree_first() -> None:
    async with world() as w:
        op = w["operator"].fed
        channel = await altitudes_and_operator_sessions(w, "uav-a")
        channel.sessions.forget("uav-b")  # a key exchange first: in a task of its own
        assert channel.sends_now("uav-a") and not channel.sends_now("uav-b")
        content = {"action": "get-latest", "labels": ["heli-altitude"]}
        result = await op.global_request(content, deadline=WAIT, select="newest")
        assert sorted(result.answers) == ["uav-a", "uav-b"] and result.chosen == "uav-b"
        assert result.no_answer == [] and result.refused == {}
        assert channel.sends_now("uav-b")  # agreed on the way


# -- label search --------------------------------------------------------------------------------


async def test_search_labels_and_a_malformed_formula() -> None:
    async with world() as w:
        b = w["uav-b"].fed
        found = await b.request_from(
            "uav-a",
            {
                "action": "search-labels",
                "formula": "(all ?x (and (Car ?x) (Color ?x blue) (OnRoad ?x road7)))",
            },
        )
        assert found == {"labels": ["car5-state"]}
        reason = await refusal(
            b.request_from(
                "uav-a", {"action": "search-labels", "formula": "(all ?x (and (Car ?x) (Color"}
            )
        )
        assert reason == "'(' at position 22 is never closed"
        # Asked of everyone, the answers fused into one set of labels.
        everywhere = await b.global_request(
            {"action": "search-labels", "formula": "(all ?x (and (Car ?x) (Color ?x blue)))"},
            deadline=WAIT,
            select=lambda answers: sorted({s for a in answers.values() for s in a["labels"]}),
        )
        assert sorted(everywhere.answers) == ["operator", "uav-a"]
        assert everywhere.value == ["car5-state"]


# -- membership ---------------------------------------------------------------------------------


async def test_leave_and_join_are_seen_in_the_others_global_directory() -> None:
    async with world() as w:
        a, b, op = w["uav-a"], w["uav-b"], w["operator"]
        await b.fed.create_stream("uav-a", ["car5-state"])  # a stream from A to B
        watcher = await op.platform.add(Agent("watcher"))
        async with (
            b.fed.membership() as seen_by_b,
            await subscribe(
                watcher, "federation@uav-b", {"membership": True}, ontology=ONTOLOGY, timeout=WAIT
            ) as remote,
        ):
            # who a global request asks, kept between requests while the directory stays
            assert list(b.fed.providers()) == ["operator", "uav-a"]
            assert list(b.fed.providers(include_self=True)) == ["operator", "uav-a", "uav-b"]
            b.fed.providers().clear()  # the caller's own copy
            assert list(b.fed.providers()) == ["operator", "uav-a"]
            await a.fed.leave()
            assert not a.fed.joined
            assert await next_event(seen_by_b, MembershipEvent("left", "uav-a"))
            assert await next_event(remote, {"event": "left", "platform": "uav-a"})
            assert b.platform.global_df is not None
            listed = b.platform.global_df.search(type=FEDERATION_SERVICE_TYPE)
            assert sorted(s.platform for s in listed) == ["operator", "uav-b"]
            assert b.fed.members == ["operator", "uav-b"]
            assert list(b.fed.providers()) == ["operator"]
            assert list(b.fed.providers(include_self=True)) == ["operator", "uav-b"]
            # The stream set up before keeps flowing; new requests from outside are refused.
            assert len(a.exporter.running) == 1
            assert "access denied" in await refusal(
                b.fed.request_from("uav-a", {"action": "list-labels"}, timeout=WAIT)
            )

            await a.fed.join()
            assert a.fed.joined
            assert await next_event(seen_by_b, MembershipEvent("joined", "uav-a"))
            assert await next_event(remote, {"event": "joined", "platform": "uav-a"})
            assert b.fed.members == ["operator", "uav-a", "uav-b"]
            assert b.fed.providers() == {
                "operator": "federation@operator",
                "uav-a": "federation@uav-a",
            }
            assert await b.fed.request_from("uav-a", {"action": "list-labels"}) == {
                "labels": sorted(TABLES["uav-a"])
            }


async def test_a_vanished_platform_is_reported_gone_within_a_second() -> None:
    async with world() as w:
        a, b, op = w["uav-a"], w["uav-b"], w["operator"]
        await a.fed.create_stream("uav-b", ["car5-state"], to_units=["uav-a", "operator"])
        assert len(b.exporter.running) == 2
        watcher = await op.platform.add(Agent("watcher"))
        async with (
            b.fed.membership() as seen_by_b,
            await subscribe(
                watcher, "federation@uav-b", {"membership": True}, ontology=ONTOLOGY, timeout=WAIT
            ) as remote,
        ):
            assert "uav-a" in b.fed.providers()
            loop = asyncio.get_running_loop()
            started = loop.time()
            # uav-a's connection goes at once, as when its process is killed.
            await a.transport.aclose()
            async with asyncio.timeout(1.0):
                assert await next_event(seen_by_b, MembershipEvent("gone", "uav-a"))
                assert await next_event(remote, {"event": "gone", "platform": "uav-a"})
            assert loop.time() - started < 1.0
            assert "uav-a" not in b.fed.members and "uav-a" not in b.fed.providers()
            # The export to uav-a stopped; the one to the operator goes on.
            assert [e.receiver for e in b.exporter.running] == ["operator"]
            (record,) = b.fed.exports.values()
            assert record.receivers == ["operator"]


async def test_membership_subscription_needs_its_content() -> None:
    async with world() as w:
        reason = await refusal(
            subscribe(w["uav-b"].fed, "federation@uav-a", {"members": 1}, ontology=ONTOLOGY)
        )
        assert "membership" in reason


# -- a plain get-latest's answer handed over to its reply, without the reply's copy ------------


class _Code(IntEnum):
    A = 1


class _Name(StrEnum):
    A = "a"


class _Float(float):
    pass


class _Str(str):
    pass


class _Int(int):
    pass


class _Rows:
    """What latest_contents reads of an instance: one clock reading and a sample per label."""

    def __init__(self, now: Any, rows: list[Any]) -> None:
        self.now, self.rows = now, rows

    def latest_many(self, labels: list[str]) -> tuple[Any, list[Any]]:
        return self.now, list(self.rows)


_odd = st.sampled_from(
    [_Code.A, _Name.A, _Float(1.5), _Str("x"), _Int(3), (1, 2), object(), b"x", {1: 2}]
)
_leaf = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=2**64)
    | st.floats()  # NaN and infinities included
    | st.text(max_size=3)
    | _odd
)
_sample_value = st.recursive(
    _leaf,
    lambda inner: (
        st.lists(inner, max_size=3)
        | st.dictionaries(
            st.text(max_size=2) | st.sampled_from([_Str("k"), 1, _Code.A]), inner, max_size=2
        )
        | st.tuples(inner)
    ),
    max_leaves=6,
)
_time = st.integers(-(2**70), 2**70) | st.floats() | st.sampled_from([_Int(5), _Float(2.0)])
_sample = st.none() | st.tuples(_sample_value, _time, _time)


def _exact(value: Any) -> Any:
    """``value``'s types, all the way down (an equal value of another type differs here)."""
    if type(value) is dict:
        return {(type(k), k): _exact(v) for k, v in value.items()}
    if type(value) is list:
        return [_exact(v) for v in value]
    return type(value), repr(value)


def _reply_outcome(content: Any) -> tuple[Any, ...]:
    question = ACLMessage.build(
        performative=Performative.QUERY_REF,
        sender="federation@operator",
        receivers=["federation@uav-a"],
        content={"action": "get-latest", "labels": ["x"]},
        conversation_id="c-1",
        reply_with="r-1",
    )
    try:
        answer = question.reply(Performative.INFORM, content, sender="federation@uav-a")
    except Exception as exc:  # the type and the words the handler sees
        return type(exc).__name__, str(exc)
    try:
        wire: Any = answer.to_json()
    except Exception as exc:
        wire = (type(exc).__name__, str(exc))
    return repr(answer), _exact(answer.content), answer.model_fields_set, wire


@settings(max_examples=400, deadline=None)
@given(
    st.integers(0, 2**62) | _time,
    st.lists(
        st.tuples(st.text(min_size=1, max_size=3) | st.just(_Str("s")), _sample),
        max_size=4,
        unique_by=lambda drawn: drawn[0],
    ),
)
def test_a_handed_over_latest_is_the_reply_the_copy_made(now: Any, drawn: list[Any]) -> None:
    """_latest_reply: the reply it hands its answer to is the one the copied answer made."""
    labels = [label for label, _ in drawn]
    rows = [sample for _, sample in drawn]
    fake = SimpleNamespace(
        instance=_Rows(now, rows),
        _locals=lambda labels, asker: labels,
        _answers=lambda req, labels, local: "answered one by one",
        _resolved_by=None,  # a translator whose translations are not kept
        _remember=lambda key, labels, local, only_str: None,
        translator=None,
    )
    # before: each value as jsonable makes it, the answer copied and checked by the reply
    try:
        query_time = now / NS_PER_S
        old: Any = dict.fromkeys(labels)
        for label, s in zip(labels, rows, strict=True):
            samples = [] if s is None else [[jsonable(s[0]), s[1] / NS_PER_S, s[2] / NS_PER_S]]
            old[label] = {"query_time": query_time, "samples": samples}
    except Exception:
        old = "answered one by one"
    new = FederationAgent._latest_reply(fake, labels, "operator")  # type: ignore[arg-type]
    if isinstance(new, HandedOver):
        assert new.value == old or repr(new.value) == repr(old)  # NaN is not equal to itself
        assert _reply_outcome(new) == _reply_outcome(old)
    else:
        assert _reply_outcome(new) == _reply_outcome(old)
    # the quick answer of plain values and labels is handed over; nothing else is
    plain = old != "answered one by one" and all(
        type(x) in (str, int, float, bool, type(None))
        for x in [
            *labels,
            now / NS_PER_S,
            *(v for s in rows if s is not None for v in (s[0], s[1] / NS_PER_S, s[2] / NS_PER_S)),
        ]
    )
    assert isinstance(new, HandedOver) == plain


async def test_a_durable_stream_created_again_is_cancelled_by_its_first_id() -> None:
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        first = await b.fed.create_stream("uav-a", ["car5-state"], durable=True)
        async with b.fed.membership() as seen:
            await a.fed.leave()
            assert await next_event(seen, MembershipEvent("left", "uav-a"))
            await a.fed._end(a.fed.exports[first])  # as after a restart: its export is gone
            await a.fed.join()
            assert await next_event(seen, MembershipEvent("joined", "uav-a"))
        await until(lambda: len(a.exporter.running) == 1, "created again by itself")
        assert a.exporter.running[0] is not None and first not in a.fed.exports
        await b.fed.cancel_stream("uav-a", first)  # the only id the user ever got
        assert a.exporter.running == [] and b.fed._durable["uav-a"] == {}


async def test_a_durable_stream_that_still_runs_is_not_asked_for_again() -> None:
    # the provider only left and came back: its export still runs, nothing to re-create
    async with world() as w:
        a, b = w["uav-a"], w["uav-b"]
        first = await b.fed.create_stream("uav-a", ["car5-state"], durable=True)
        async with b.fed.membership() as seen:
            await a.fed.leave()
            await next_event(seen, MembershipEvent("left", "uav-a"))
            await a.fed.join()
            await next_event(seen, MembershipEvent("joined", "uav-a"))
        # the re-ask, started with the return's news: refused (it still runs), it gives up
        asking = [t for t in asyncio.all_tasks() if t.get_name().endswith(".durable:uav-a")]
        assert asking, "uav-a's return asked for nothing"
        async with asyncio.timeout(WAIT):
            await asyncio.wait(asking)
        assert len(a.exporter.running) == 1 and b.fed._durable["uav-a"][first].current == first


def test_another_platform_cannot_ask_for_a_grid_finer_than_a_millisecond() -> None:
    import pytest
    from pydantic import ValidationError

    from federation._gateway_service import PolicySpec
    from federation._service_content import CreateStream

    with pytest.raises(ValidationError, match="sample-period"):
        CreateStream.model_validate(
            {"action": "create-stream", "labels": ["car5-state"], "sample-period": 1e-9}
        )
    with pytest.raises(ValidationError, match="sample_period"):
        PolicySpec(sample_period=1e-9)
    assert PolicySpec(sample_period=0.001).to_policy(0).sample_period == 0.001


# -- global requests: a send that fails partway ---------------------------------------------


@pytest.mark.parametrize("in_turn", [True, False])
async def test_a_global_request_whose_send_fails_still_asks_the_others(in_turn: bool) -> None:
    """In turn (a session held) or in a task: the failure is reported, the rest answer."""
    from agents import TransportError

    async with world() as w:
        op = w["operator"].fed
        channel = await altitudes_and_operator_sessions(w, "uav-a", "uav-b")
        if not in_turn:
            channel.sends_now = lambda platform: False  # type: ignore[method-assign]
        # the link to uav-a fails, both ways a message goes out (awaited, or at once)
        transport = w["operator"].platform.transport
        publish, publish_now = transport.publish, transport.publish_nowait

        async def failing(key: str, payload: bytes, **kw: Any) -> None:
            if key.endswith("/acl/uav-a"):
                raise TransportError("link down")
            await publish(key, payload, **kw)

        def failing_now(key: str, payload: bytes) -> None:
            if key.endswith("/acl/uav-a"):
                raise TransportError("link down")
            publish_now(key, payload)

        transport.publish = failing  # type: ignore[method-assign]
        transport.publish_nowait = failing_now  # type: ignore[method-assign]
        content = {"action": "get-latest", "labels": ["heli-altitude"]}
        result = await op.global_request(content, deadline=WAIT, select="newest")
        assert result.refused == {"uav-a": "unreachable: TransportError: link down"}
        assert sorted(result.answers) == ["uav-b"] and result.no_answer == []
