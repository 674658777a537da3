"""A member shares only what it agreed to share, with whom it agreed (issue 11, items 1-5, 7).

The attacker here is a *member*: ``uav-m`` holds a key in the federation's trust file and
runs our own library (a whole `FederationPlatform`), so everything it sends is
authenticated. The victims are real spawned processes (``uav-a``, ``uav-b``: each a
`FederationPlatform` from its config file, on zenoh in peer mode over loopback), asked
over a pipe for their counters and audit records. Each test attacks as the issue found
it possible, and asserts the refusal (or the drop), its count and its audit record:

1. the Gateway Agent is private by default; opened, it still keeps ``import/`` labels
2. ``reply_to`` naming a third platform is refused: no answers are reflected to it
3. ``to-units`` naming a third platform needs that platform's consent
4. batches nobody asked for are dropped, counted and audited (summed up), boundedly
5. export slots and history are limited per requesting platform
7. per-label sharing rules of the config: who may query / stream which labels

and, in one process, that drops under invented sender names are audited boundedly too.

Every wait is bounded, every process killed on the way out; federations are unique.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import multiprocessing
import uuid
from collections.abc import AsyncIterator, Iterable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

import pytest
from test_faults import Pipe, killed_at_exit, until
from test_proxies import Net, stream_key

from agents import (
    Agent,
    MessageTemplate,
    Performative,
    Refused,
    SubscriptionEnded,
    new_id,
    on,
    query_ref,
    request,
    subscribe,
    wire_key,
)
from agents._platform import REFUSAL_AUDIT_INTERVAL, REFUSALS_ONE_BY_ONE
from agents.keys import gen_keys, trust_keys
from agents.transports import MemoryHub, free_tcp_port
from dyknow_core import seconds_to_ns
from federation import FederationPlatform, PlatformConfig, PlatformConfigError, SharingSettings
from federation._batch import pack_batch
from federation._service import Denied
from federation._sessions import InterfaceSessions, PlainSessions

pytestmark = pytest.mark.timeout(180)

START = 40.0  # a spawned interpreter imports zenoh, pydantic and DyKnow: generous on a busy box
# A world's whole start (victims ready, members known, snapshots taken) shares this bound,
# under the tests' own (120 s at least), so a slow start fails naming what is missing
SETUP = 2 * START
WAIT = 15.0
P = Performative

VOCABULARY = {
    "name": "traffic",
    "labels": {
        "heli-altitude": "this platform's altitude, m",
        "{object}-state": "the state of a tracked object, e.g. car5-state",
    },
}
MAPPING = {"heli-altitude": "nav/alt", "{object}-state": "cars/{object}/state"}
CARS = 40  # car0 … car39: what each UAV tracks (local labels cars/carN/state)
SECRET = "mission/plan"  # a local label with no semantic label: it never leaves


# -- the victim: a spawned platform answering questions over a pipe ------------------------------


def victim_main(config_path: str, conn: Connection) -> None:
    """A UAV platform until told to exit: sources flowing, counters on request."""
    config = PlatformConfig.from_dict(json.loads(Path(config_path).read_text()), source=config_path)
    asyncio.run(_victim(config, conn))


def _rss_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _stats(p: FederationPlatform) -> dict[str, Any]:
    fed = p.federation_agent
    gdf = p.agents.global_df
    return {
        "platform": {k: v for k, v in dataclasses.asdict(p.agents.stats).items() if k != "senders"},
        "df_stale": gdf.stale if gdf is not None else None,
        "df_invalid": gdf.invalid if gdf is not None else None,
        # of those stale, the ones the event gate shed before any signature check
        "df_stale_shed": gdf.event_gate.stale if gdf is not None and gdf.event_gate else 0,
        # the platforms whose signed snapshot came (none of theirs still asked)
        "df_listed": gdf.listed if gdf is not None else [],
        # the platforms its Federation Agent takes for members (from the directory)
        "members": p.members,
        # the directory's warnings, as logged (their number is bounded per signer)
        "df_warnings": list(_DF_WARNINGS),
        "audit": [dict(r) for r in p.interface.audit.records],
        "refusals": dict(fed.refusals),
        # answered as they came (`Agent.answer_at_once`): the attacks met that path too
        "at_once": {
            "federation": fed.stats.answered_at_once,
            "gateway": p.gateway.stats.answered_at_once,
        },
        "gateway": dataclasses.asdict(p.gateway.gateway_stats),
        "reply_to_refused": p.interface.reply_to_refused,
        "imports": p.importer.stats(),
        "labels": p.instance.labels(),
        "locations": sorted(p.instance.locations),
        "exports": [(e.receiver, e.semantic_label, e.sent) for e in p.exporter.exports()],
        "agreed": {
            i: {"requester": r.requester, "receivers": r.receivers, "labels": r.labels}
            for i, r in fed.exports.items()
        },
        "senders": {k: s.accepted for k, s in p.agents.stats.senders.items()},
        "rss_kb": _rss_kb(),
        "membership_subscribers": len(fed._subscribers),
        "df_subscribers": len(p.agents.df._subscriptions) if p.agents.df is not None else 0,
        "df_subscriptions_refused": (
            p.agents.df.subscriptions_refused if p.agents.df is not None else 0
        ),
    }


async def _feed(p: FederationPlatform) -> None:
    """A UAV's own streams: every car it tracks and its altitude, 20 times a second."""
    sources = [p.instance.add_source(f"cars/car{i}/state") for i in range(CARS)]
    sources.append(p.instance.add_source("nav/alt"))
    sources.append(p.instance.add_source(SECRET))
    k = 0
    while True:
        now = p.instance.clock.now()
        for s in sources:
            s.push({"k": k, "from": p.name}, now)
        k += 1
        await asyncio.sleep(0.05)


_DF_WARNINGS: list[str] = []


class _Kept(logging.Handler):
    """Keeps the messages logged (the directory's warnings, for `_stats`)."""

    def emit(self, record: logging.LogRecord) -> None:
        _DF_WARNINGS.append(record.getMessage())


class _Stuck(Agent):
    """An agent whose first message holds its handler: its mailbox of 2 then fills."""

    def __init__(self, name: str) -> None:
        super().__init__(name, mailbox_size=2)

    @on(MessageTemplate(P.INFORM))
    async def _hold(self, message: Any) -> None:
        await asyncio.Event().wait()


async def _victim(config: PlatformConfig, conn: Connection) -> None:
    pipe = Pipe(conn)
    df_log = logging.getLogger("agents._df")
    df_log.addHandler(_Kept(logging.WARNING))
    async with FederationPlatform(config) as p:

        async def serve() -> None:
            while True:
                msg = await next_command(pipe)
                if msg[0] == "stats":
                    pipe.send("stats", _stats(p))
                elif msg[0] == "ask":
                    _, provider, labels = msg
                    try:
                        got = await p.federation_agent.create_stream(provider, labels, timeout=WAIT)
                        pipe.send("asked", got)
                    except Exception as exc:
                        pipe.send("asked", f"error: {exc}")
                elif msg[0] == "quiet":  # its own streams stop: their history stops growing
                    feed.cancel()
                    pipe.send("quiet")
                elif msg[0] == "stuck":  # an agent whose mailbox fills (see `_Stuck`)
                    await p.agents.add(_Stuck(msg[1]))
                    pipe.send("stuck")
                elif msg[0] == "limits":  # the gateway's, low: an attack reaches them fast
                    p.gateway.max_subscriptions = msg[1]
                    p.gateway.service.max_streams = msg[2]
                    if len(msg) > 3:  # what one other platform may hold of them
                        p.gateway.max_subscriptions_per_platform = msg[3]
                        p.gateway.service.max_streams_per_platform = msg[4]
                    pipe.send("limits")
                elif msg[0] == "unprocess":  # the operator removes a process by hand
                    p.instance.remove_process(msg[1])
                    pipe.send("unprocess")
                elif msg[0] == "exit":
                    return

        feed = asyncio.ensure_future(_feed(p))
        pipe.send("ready", config.name)
        await serve()
        feed.cancel()


async def next_command(pipe: Pipe) -> tuple[Any, ...]:
    """The next message from the test, whatever its kind (the test gone: exit)."""
    msg = await pipe.inbox.get()
    return ("exit",) if msg[0] == "eof" else tuple(msg)


# -- the federation: victims spawned, the attacker and honest peers here -----------------------


@dataclass
class World:
    """Spawned victims (by name, with their pipes) and in-process platforms (by name)."""

    federation: str
    pipes: dict[str, Pipe] = field(default_factory=dict)
    here: dict[str, FederationPlatform] = field(default_factory=dict)

    async def stats(self, name: str) -> dict[str, Any]:
        """The victim's counters and audit records, now."""
        self.pipes[name].send("stats")
        return (await self.pipes[name].expect("stats", WAIT))[1]

    async def ask(self, name: str, provider: str, labels: list[str]) -> str:
        """Have the victim's Federation Agent ask ``provider`` for ``labels`` (to itself)."""
        self.pipes[name].send("ask", provider, labels)
        return str((await self.pipes[name].expect("asked", WAIT + 5))[1])

    async def until_stats(self, name: str, check: Any, what: str) -> dict[str, Any]:
        """Poll the victim's stats until ``check(stats)`` holds (counters have no event)."""
        try:
            async with asyncio.timeout(WAIT):
                while True:
                    s = await self.stats(name)
                    if check(s):
                        return s
                    await asyncio.sleep(0.1)
        except TimeoutError:
            raise AssertionError(f"{name}: {what}: not within {WAIT} s") from None


def _config(
    tmp: Path, federation: str, name: str, port: int, seed: int | None, **more: Any
) -> Path:
    data = {
        "name": name,
        "federation": federation,
        "key": str(tmp / "keys" / f"{name}.key"),
        "trust": str(tmp / "trust.json"),
        "vocabulary": VOCABULARY,
        "mapping": {"vocabulary": "traffic", "labels": MAPPING},
        "audit": str(tmp / f"audit-{name}.jsonl"),
        "transport": {
            "kind": "zenoh",
            "mode": "peer",
            "listen": [f"tcp/127.0.0.1:{port}"],
            "connect": [] if seed is None else [f"tcp/127.0.0.1:{seed}"],
        },
        **more,
    }
    path = tmp / f"{name}.json"
    path.write_text(json.dumps(data))
    return path


@contextlib.asynccontextmanager
async def world(
    tmp: Path,
    spawned: Iterable[str],
    here: Iterable[str] = ("uav-m",),
    **configs: dict[str, Any],
) -> AsyncIterator[World]:
    """Victims ``spawned`` (children), ``here`` in this process; ``configs`` by name (``_``)."""
    spawned, here = list(spawned), list(here)
    names = spawned + here
    federation = f"authz-{uuid.uuid4().hex[:8]}"
    pubs = [gen_keys(n, tmp / "keys")[2] for n in names]
    trust_keys(tmp / "trust.json", pubs, federation=federation)
    ports = {n: free_tcp_port() for n in names}
    seed = ports[names[0]]
    paths = {
        n: _config(
            tmp,
            federation,
            n,
            ports[n],
            None if n == names[0] else seed,
            **configs.get(n.replace("-", "_"), {}),
        )
        for n in names
    }
    ctx = multiprocessing.get_context("spawn")
    procs: list[BaseProcess] = []
    w = World(federation)
    loop = asyncio.get_running_loop()
    deadline = loop.time() + SETUP
    with killed_at_exit(procs):
        async with contextlib.AsyncExitStack() as stack:
            for n in spawned:
                parent, child = ctx.Pipe()
                proc = ctx.Process(target=victim_main, args=(str(paths[n]), child), name=n)
                procs.append(proc)
                proc.start()
                child.close()
                w.pipes[n] = Pipe(parent)
                stack.callback(w.pipes[n].close)
            for n in here:
                cfg = PlatformConfig.from_dict(json.loads(paths[n].read_text()), source=str(n))
                w.here[n] = p = await stack.enter_async_context(FederationPlatform(cfg))
                task = asyncio.ensure_future(_feed(p))
                stack.callback(task.cancel)
            for n in spawned:
                try:
                    await w.pipes[n].expect("ready", deadline - loop.time())
                except TimeoutError:
                    raise AssertionError(f"{n}: not ready within {SETUP:g} s") from None
            for p in w.here.values():
                try:
                    await until(
                        lambda p=p: set(names) <= set(p.members),
                        "every member",
                        deadline - loop.time(),
                    )
                except TimeoutError:
                    missing = sorted(set(names) - set(p.members))
                    raise AssertionError(
                        f"{p.name}: members {missing} not known within {SETUP:g} s"
                    ) from None
            await _snapshots_taken(w, names, spawned, deadline - loop.time())
            yield w
            for n in spawned:
                w.pipes[n].send("exit")


async def _snapshots_taken(w: World, names: list[str], spawned: list[str], within: float) -> None:
    """Until each victim has every other member's signed snapshot and takes it for a member.

    A victim takes each member's signed snapshot when its presence comes, and asks again
    when an event came meanwhile: an event a test sends before that answer is taken may be
    counted stale (the answer reflects it), and the victim's Federation Agent may not take
    the member for one yet. One bound for all the victims; past it, what each one lacks.
    """
    lacking: dict[str, str] = {n: "no stats answered" for n in spawned}
    try:
        async with asyncio.timeout(within):
            while lacking:
                for n in list(lacking):
                    s = await w.stats(n)
                    others = set(names) - {n}
                    unlisted = sorted(others - set(s["df_listed"]))
                    strangers = sorted(others - set(s["members"]))
                    if unlisted or strangers:
                        lacking[n] = f"no snapshot of {unlisted}, not members {strangers}"
                    else:
                        del lacking[n]
                if lacking:
                    await asyncio.sleep(0.1)
    except TimeoutError:
        why = "; ".join(f"{n}: {what}" for n, what in lacking.items())
        raise AssertionError(f"snapshots not taken within {SETUP:g} s: {why}") from None


async def mallory(w: World) -> Agent:
    """The attacker's agent on uav-m."""
    m = w.here["uav-m"]
    return m.agents.agent("mallory") or await m.agents.add(Agent("mallory"))


def audited(stats: dict[str, Any], **match: Any) -> list[dict[str, Any]]:
    """The victim's audit records whose fields equal ``match`` (``reason`` a prefix)."""
    prefix = match.pop("reason", "")
    return [
        r
        for r in stats["audit"]
        if str(r.get("reason")).startswith(prefix) and all(r.get(k) == v for k, v in match.items())
    ]


def in_file(tmp: Path, name: str, record: dict[str, Any]) -> bool:
    """Whether ``record`` is in the victim's JSON-lines audit file too."""
    path = tmp / f"audit-{name}.jsonl"
    return path.exists() and record in [json.loads(x) for x in path.read_text().splitlines()]


async def audited_in_file(
    tmp: Path, stats: dict[str, Any], n: int, **match: Any
) -> list[dict[str, Any]]:
    """uav-a's ``n`` audit records that match (`audited`), the last one in its file too."""
    recs = audited(stats, **match)
    assert len(recs) == n, recs
    await until(lambda: in_file(tmp, "uav-a", recs[-1]), "the record in the audit file")
    return recs


async def refusal(coro: Any) -> str:
    """The reason of the refuse ``coro`` ends with."""
    with pytest.raises(Refused) as info:
        await coro
    assert info.value.message is not None
    return str(info.value.message.content)


# -- 1. the Gateway Agent ------------------------------------------------------------------------


async def test_the_gateway_agent_is_private_by_default(tmp_path: Path) -> None:
    async with asyncio.timeout(120), world(tmp_path, ["uav-a"], ["uav-c", "uav-m"]) as w:
        # uav-a imports uav-c's car7-state, as the attack found it
        assert (await w.ask("uav-a", "uav-c", ["car7-state"])).startswith("x-")
        await w.until_stats(
            "uav-a",
            lambda s: "import/uav-c/car7-state" in s["labels"],
            "uav-c's stream imported",
        )
        m = await mallory(w)
        attacks = [
            {"action": "list-labels"},
            {"action": "query", "label": "import/uav-c/car7-state"},
            {"action": "query", "label": SECRET},
            {
                "action": "create-stream",
                "label": "cars/car5/state",
                "output": "import/uav-c/car7-state",
            },
        ]
        for content in attacks:
            reason = await refusal(request(m, "gateway@uav-a", content, ontology="dyknow"))
            assert reason.startswith("access denied: gateway@uav-a offers no service")
        s = await w.stats("uav-a")
        recs = audited(s, verdict="refused", sender="mallory@uav-m", reason="access denied")
        assert len(recs) == len(attacks)
        assert all(r["receivers"] == ["gateway@uav-a"] for r in recs)
        await until(lambda: in_file(tmp_path, "uav-a", recs[-1]), "the record in the audit file")
        # nothing was created; uav-c's import still lands where it should
        assert s["gateway"]["reserved_refused"] == 0  # never reached the gateway
        rec = next(i for i in s["imports"]["imports"] if i["sender"] == "uav-c")
        assert rec["local_label"] == "import/uav-c/car7-state"
        assert "label-taken" not in rec["dropped_samples"]


async def test_an_opened_gateway_keeps_import_labels_and_creates_none(tmp_path: Path) -> None:
    opened = {"sharing": {"gateway": "protected"}}
    async with (
        asyncio.timeout(120),
        world(tmp_path, ["uav-a"], ["uav-c", "uav-m"], uav_a=opened) as w,
    ):
        m = await mallory(w)
        # before uav-a asks uav-c: the attacker tries to take the label first
        create = {
            "action": "create-stream",
            "label": "cars/car5/state",
            "output": "import/uav-c/car7-state",
        }
        reason = await refusal(request(m, "gateway@uav-a", create, ontology="dyknow"))
        assert "'import/uav-c/car7-state' is reserved" in reason
        assert (await w.ask("uav-a", "uav-c", ["car7-state"])).startswith("x-")
        s = await w.until_stats(
            "uav-a",
            lambda s: any(i["injected"] for i in s["imports"]["imports"] if i["sender"] == "uav-c"),
            "uav-c's samples injected",
        )
        read = {"action": "query", "label": "import/uav-c/car7-state"}
        reason = await refusal(request(m, "gateway@uav-a", read, ontology="dyknow"))
        assert "reserved" in reason and "only agents of this platform" in reason
        listed = await request(m, "gateway@uav-a", {"action": "list-labels"}, ontology="dyknow")
        assert isinstance(listed, dict)
        assert SECRET in listed["labels"]  # opened by its operator: local labels are visible
        assert not [lb for lb in listed["labels"] if lb.startswith("import/")]
        # a read of a label it may see is answered as it comes; the reserved ones were not
        got = await request(
            m, "gateway@uav-a", {"action": "query", "label": SECRET}, ontology="dyknow"
        )
        assert isinstance(got, dict) and got["samples"]
        s = await w.stats("uav-a")
        assert s["at_once"]["gateway"] == 1
        assert s["gateway"]["reserved_refused"] == 2
        recs = audited(s, verdict="refused", stage="gateway", sender="mallory@uav-m")
        assert [r["code"] for r in recs] == ["reserved-label", "reserved-label"]
        assert all(r["reason"].startswith("reserved-label: label 'import/") for r in recs)
        await until(lambda: in_file(tmp_path, "uav-a", recs[-1]), "the record in the audit file")
        rec = next(i for i in s["imports"]["imports"] if i["sender"] == "uav-c")
        assert rec["injected"] >= 1 and "label-taken" not in rec["dropped_samples"]


async def test_an_opened_gateway_counts_and_audits_a_member_asking_labels_not_there(
    tmp_path: Path,
) -> None:
    """Probing which labels a platform has: each ask of a label not there, by a plain read,
    a query-ref, another kind of query, a create-stream's source or a subscribe, is
    refused, counted and audited with the reason the member was told (naming no reserved
    label), one by one: a few are within the member's budget (a flood is summed up, the
    test after next). The lane leaves such a read to the event loop:
    `test_answer_on_thread.py`."""
    opened = {"sharing": {"gateway": "protected"}}
    async with (
        asyncio.timeout(120),
        world(tmp_path, ["uav-a"], ["uav-c", "uav-m"], uav_a=opened) as w,
    ):
        assert (await w.ask("uav-a", "uav-c", ["car7-state"])).startswith("x-")
        await w.until_stats(
            "uav-a",
            lambda s: "import/uav-c/car7-state" in s["labels"],
            "uav-c's stream imported",
        )
        m = await mallory(w)
        gw = "gateway@uav-a"
        # a label it may read is answered
        read = {"action": "query", "label": SECRET}
        assert (await request(m, gw, read, ontology="dyknow"))["samples"]
        before = await w.stats("uav-a")
        probe = "mission/target"
        plain = {"action": "query", "label": probe}
        told = [await refusal(request(m, gw, plain, ontology="dyknow")) for _ in range(3)]
        told.append(await refusal(query_ref(m, gw, {"label": probe}, ontology="dyknow")))
        told.append(
            await refusal(
                request(m, gw, {**plain, "kind": "between", "from": 0.0}, ontology="dyknow")
            )
        )
        create = {"action": "create-stream", "label": probe, "output": "op/probe"}
        told.append(await refusal(request(m, gw, create, ontology="dyknow")))
        told.append(await refusal(subscribe(m, gw, {"label": probe}, ontology="dyknow")))
        seen = sorted(lb for lb in before["labels"] if not lb.startswith("import/"))
        unknown = f"unknown label {probe!r} (known labels: {', '.join(seen[:8])}, …)"
        assert told == [unknown] * 7
        s = await w.until_stats(
            "uav-a",
            lambda s: len(audited(s, stage="gateway", code="unknown-label")) >= 7,
            "the refusals audited",
        )
        assert s["gateway"]["unknown_label_refused"] == 7
        assert s["gateway"]["reserved_refused"] == 0
        recs = audited(s, verdict="refused", stage="gateway", sender="mallory@uav-m")
        assert [(r["code"], r["from"], r["reason"]) for r in recs] == [
            ("unknown-label", "uav-m", f"unknown-label: {unknown}")
        ] * 7
        assert [r["performative"] for r in recs] == ["request"] * 3 + [
            "query-ref",
            "request",
            "request",
            "subscribe",
        ]
        assert all(r["receivers"] == [gw] for r in recs)
        # a member's few mistakes are all seen one by one, none summed up (within its budget)
        assert len(recs) <= REFUSALS_ONE_BY_ONE
        assert not [r for r in s["audit"] if r.get("stage") == "gateway" and r.get("count")]
        await until(lambda: in_file(tmp_path, "uav-a", recs[-1]), "the record in the audit file")


async def test_a_member_exhausting_an_opened_gateways_limits_or_probing_outputs_is_refused(
    tmp_path: Path,
) -> None:
    """A member creating streams and subscribing past the gateway's limits is refused,
    counted and audited one by one; so is its create-stream whose output is taken (it would
    tell which labels exist), with the reason it was told."""
    opened = {"sharing": {"gateway": "protected"}}
    async with (
        asyncio.timeout(120),
        world(tmp_path, ["uav-a"], ["uav-m"], uav_a=opened) as w,
    ):
        w.pipes["uav-a"].send("limits", 2, 2)  # subscriptions, created streams
        await w.pipes["uav-a"].expect("limits", WAIT)
        m = await mallory(w)
        gw = "gateway@uav-a"

        def create(output: str) -> dict[str, Any]:
            return {"action": "create-stream", "label": SECRET, "output": output}

        assert await request(m, gw, create("op/s0"), ontology="dyknow") == {
            "label": "op/s0",
            "source": SECRET,
        }
        taken = [
            await refusal(request(m, gw, create(lb), ontology="dyknow")) for lb in ("op/s0", SECRET)
        ]
        assert taken == [f"label {lb!r} is already published" for lb in ("op/s0", SECRET)]
        await request(m, gw, create("op/s1"), ontology="dyknow")
        streams = await refusal(request(m, gw, create("op/s2"), ontology="dyknow"))
        assert streams == "too many created streams (limit 2)"
        held = [await subscribe(m, gw, {"label": SECRET}, ontology="dyknow") for _ in range(2)]
        subs = await refusal(subscribe(m, gw, {"label": SECRET}, ontology="dyknow"))
        assert subs == "too many subscriptions (limit 2)"
        s = await w.until_stats(
            "uav-a",
            lambda s: len(audited(s, stage="gateway", sender="mallory@uav-m")) >= 4,
            "the refusals audited",
        )
        assert s["gateway"]["limit_refused"] == 2
        assert s["gateway"]["taken_label_refused"] == 2
        assert s["gateway"]["subscriptions"] == 2
        recs = audited(s, verdict="refused", stage="gateway", sender="mallory@uav-m")
        assert [(r["code"], r["from"], r["performative"], r["reason"]) for r in recs] == [
            ("label-taken", "uav-m", "request", f"label-taken: {taken[0]}"),
            ("label-taken", "uav-m", "request", f"label-taken: {taken[1]}"),
            ("stream-limit", "uav-m", "request", f"stream-limit: {streams}"),
            ("subscription-limit", "uav-m", "subscribe", f"subscription-limit: {subs}"),
        ]
        assert all(r["receivers"] == [gw] for r in recs)
        await until(lambda: in_file(tmp_path, "uav-a", recs[-1]), "the record in the audit file")
        for h in held:
            await h.cancel()


async def test_one_member_cannot_take_every_slot_of_an_opened_gateway(tmp_path: Path) -> None:
    """A member holds at most its share of an opened gateway's created streams and
    subscriptions: past it refused (the reason, counted, audited), while another member
    still creates and subscribes; a slot of its freed (its subscription cancelled, its
    stream removed by the operator), it may again."""
    opened = {"sharing": {"gateway": "protected"}}
    async with (
        asyncio.timeout(150),
        world(tmp_path, ["uav-a"], ["uav-c", "uav-m"], uav_a=opened) as w,
    ):
        # subscriptions, created streams: all askers together, then one platform's share
        w.pipes["uav-a"].send("limits", 4, 4, 2, 2)
        await w.pipes["uav-a"].expect("limits", WAIT)
        m = await mallory(w)
        c = w.here["uav-c"].agents.agent("honest") or await w.here["uav-c"].agents.add(
            Agent("honest")
        )
        gw = "gateway@uav-a"

        def create(output: str) -> dict[str, Any]:
            return {"action": "create-stream", "label": SECRET, "output": output}

        for lb in ("op/s0", "op/s1"):
            assert await request(m, gw, create(lb), ontology="dyknow") == {
                "label": lb,
                "source": SECRET,
            }
        streams = await refusal(request(m, gw, create("op/s2"), ontology="dyknow"))
        assert streams == "too many created streams for uav-m (limit 2 per platform)"
        held = [await subscribe(m, gw, {"label": SECRET}, ontology="dyknow") for _ in range(2)]
        subs = await refusal(subscribe(m, gw, {"label": SECRET}, ontology="dyknow"))
        assert subs == "too many subscriptions for uav-m (limit 2 per platform)"
        # the other member is served: the attacker took its share, not every slot
        got = await request(c, gw, create("c/s0"), ontology="dyknow")
        assert got == {"label": "c/s0", "source": SECRET}
        theirs = await subscribe(c, gw, {"label": SECRET}, ontology="dyknow")
        sample = await theirs.get(timeout=WAIT)
        assert sample["label"] == SECRET and sample["samples"], sample
        s = await w.until_stats(
            "uav-a",
            lambda s: len(audited(s, stage="gateway", sender="mallory@uav-m")) >= 2,
            "the refusals audited",
        )
        assert s["gateway"]["limit_refused"] == 2
        assert s["gateway"]["subscriptions"] == 3
        recs = audited(s, verdict="refused", stage="gateway", sender="mallory@uav-m")
        assert [(r["code"], r["from"], r["performative"], r["reason"]) for r in recs] == [
            ("stream-limit", "uav-m", "request", f"stream-limit: {streams}"),
            ("subscription-limit", "uav-m", "subscribe", f"subscription-limit: {subs}"),
        ]
        assert all(r["receivers"] == [gw] for r in recs)
        assert not audited(s, stage="gateway", sender="honest@uav-c")
        await until(lambda: in_file(tmp_path, "uav-a", recs[-1]), "the record in the audit file")
        # its slots freed, the attacker may use them again: no count drifts
        await held.pop().cancel()
        held.append(await subscribe(m, gw, {"label": SECRET}, ontology="dyknow"))
        w.pipes["uav-a"].send("unprocess", "gateway:op/s0")
        await w.pipes["uav-a"].expect("unprocess", WAIT)
        got = await request(m, gw, create("op/s2"), ontology="dyknow")
        assert got == {"label": "op/s2", "source": SECRET}
        again = await refusal(request(m, gw, create("op/s3"), ontology="dyknow"))
        assert again == streams
        s = await w.stats("uav-a")
        assert s["gateway"]["limit_refused"] == 3
        for h in [*held, theirs]:
            await h.cancel()


async def test_a_member_cannot_remove_another_members_stream_at_an_opened_gateway(
    tmp_path: Path,
) -> None:
    """A stream one member created at an opened gateway is removed by that member only:
    another's remove-stream is refused (the reason, counted, audited) and the stream flows
    on; its creator's ends it (its subscriber told, one record) and frees its slot at once."""
    opened = {"sharing": {"gateway": "protected"}}
    async with (
        asyncio.timeout(150),
        world(tmp_path, ["uav-a"], ["uav-c", "uav-m"], uav_a=opened) as w,
    ):
        w.pipes["uav-a"].send("limits", 4, 4, 2, 1)  # one created stream per member
        await w.pipes["uav-a"].expect("limits", WAIT)
        m = await mallory(w)
        c = w.here["uav-c"].agents.agent("honest") or await w.here["uav-c"].agents.add(
            Agent("honest")
        )
        gw = "gateway@uav-a"

        def create(output: str) -> dict[str, Any]:
            return {"action": "create-stream", "label": SECRET, "output": output}

        remove = {"action": "remove-stream", "label": "c/s0"}
        assert await request(c, gw, create("c/s0"), ontology="dyknow") == {
            "label": "c/s0",
            "source": SECRET,
        }
        full = await refusal(request(c, gw, create("c/s1"), ontology="dyknow"))
        assert full == "too many created streams for uav-c (limit 1 per platform)"
        feed = await subscribe(c, gw, {"label": "c/s0"}, ontology="dyknow")
        assert (await feed.get(timeout=WAIT))["label"] == "c/s0"
        told = await refusal(request(m, gw, remove, ontology="dyknow"))
        assert told == "stream 'c/s0' was not created by uav-m"
        s = await w.until_stats(
            "uav-a",
            lambda s: audited(s, stage="gateway", code="not-creator"),
            "the refusal audited",
        )
        assert s["gateway"]["not_creator_refused"] == 1 and "c/s0" in s["labels"]
        (rec,) = await audited_in_file(tmp_path, s, 1, stage="gateway", code="not-creator")
        assert (rec["verdict"], rec["from"], rec["sender"], rec["performative"]) == (
            "refused",
            "uav-m",
            "mallory@uav-m",
            "request",
        )
        assert rec["reason"] == f"not-creator: {told}"
        assert (await feed.get(timeout=WAIT))["label"] == "c/s0"  # it flows on
        # its creator removes it: its subscriber is told, its slot is free at once
        assert await request(c, gw, remove, ontology="dyknow") == {"removed": "c/s0"}
        with pytest.raises(SubscriptionEnded):
            async with asyncio.timeout(WAIT):
                while True:  # the informs already sent, then the end
                    await feed.get(timeout=WAIT)
        assert await request(c, gw, create("c/s1"), ontology="dyknow") == {
            "label": "c/s1",
            "source": SECRET,
        }
        s = await w.stats("uav-a")
        assert s["gateway"]["streams_removed"] == 1 and "c/s0" not in s["labels"]
        (ended,) = await audited_in_file(tmp_path, s, 1, stage="gateway", code="remove-stream")
        assert (ended["verdict"], ended["stream"], ended["creator"], ended["sender"]) == (
            "ended",
            "c/s0",
            "honest@uav-c",
            "honest@uav-c",
        )


async def test_a_member_flooding_an_opened_gateway_with_refused_requests_cannot_flush_the_audit(
    tmp_path: Path,
) -> None:
    """A member asking, as fast as it is answered, for labels not there, for outputs
    taken, past the gateway's limits and for what a sharing rule refuses: each refused and
    counted exactly, the first `REFUSALS_ONE_BY_ONE` of an interval audited one by one
    (full reason), the rest summed up per code in records with ``count`` and the last
    reason. The audit grows by a few records a second, not by one per refusal: at its rate
    limit a member could otherwise rotate the audit file's whole history away in seconds."""
    # at the rate limit's rate, but a burst as large: a victim on a loaded machine takes a
    # backlog of envelopes in at once, and the requests the limit drops are never answered
    opened = {
        "sharing": {"gateway": "protected", **RULES["sharing"]},
        "rate_limit": {"burst": 5000},
    }
    async with (
        asyncio.timeout(170),
        world(tmp_path, ["uav-a"], ["uav-m"], uav_a=opened) as w,
    ):
        w.pipes["uav-a"].send("limits", 1, 256)  # one subscription
        await w.pipes["uav-a"].expect("limits", WAIT)
        m = await mallory(w)
        fed = w.here["uav-m"].federation_agent
        gw = "gateway@uav-a"
        held = await subscribe(m, gw, {"label": SECRET}, ontology="dyknow")
        before = await w.stats("uav-a")
        seen = sorted(lb for lb in before["labels"] if not lb.startswith("import/"))
        latest = {"action": "get-latest", "labels": ["car5-state"]}
        ruled = (
            "label 'car5-state' may not be queried by uav-m: sharing rule 'neighbours' "
            "(sharing.rules[0]) (car*-state) lets uav-c, uav-b query it"
        )

        def create(output: str) -> dict[str, Any]:
            return {"action": "create-stream", "label": SECRET, "output": output}

        # (stage, code) -> (how many, the i-th request, the reason it is told)
        attacks: dict[tuple[str, str], tuple[int, Any, Any]] = {
            ("gateway", "unknown-label"): (
                1200,
                lambda i: request(
                    m, gw, {"action": "query", "label": f"probe/{i}"}, ontology="dyknow"
                ),
                lambda i: f"unknown label 'probe/{i}' (known labels: {', '.join(seen[:8])}, …)",
            ),
            ("gateway", "label-taken"): (
                300,
                lambda i: request(m, gw, create(SECRET), ontology="dyknow"),
                lambda i: f"label {SECRET!r} is already published",
            ),
            ("gateway", "subscription-limit"): (
                300,
                lambda i: subscribe(m, gw, {"label": SECRET}, ontology="dyknow"),
                lambda i: "too many subscriptions (limit 1)",
            ),
            ("federation", "sharing-rule"): (
                300,
                lambda i: fed.request_from("uav-a", latest),
                lambda i: ruled,
            ),
            ("gateway", "stream-limit"): (
                300,
                lambda i: request(m, gw, create(f"op/s{i}"), ontology="dyknow"),
                lambda i: "too many created streams (limit 0)",
            ),
        }
        wave = 50  # requests in flight at once: well under the rate limit's burst (200)
        loop = asyncio.get_running_loop()
        pace = 800  # requests/s: the flood spans 3 s, its records kept in memory (10,000)
        sent = 0
        t0 = loop.time()
        for (_, code), (n, ask, told) in attacks.items():
            if code == "stream-limit":
                w.pipes["uav-a"].send("limits", 1, 0)  # no created stream: each refused so
                await w.pipes["uav-a"].expect("limits", WAIT)
            for start in range(0, n, wave):
                sent += min(n, start + wave) - start
                ahead = t0 + sent / pace - loop.time()
                if ahead > 0:  # a rate, not an event: nothing to await but the time
                    await asyncio.sleep(ahead)
                got = await asyncio.gather(
                    *[refusal(ask(i)) for i in range(start, min(n, start + wave))]
                )
                assert got == [told(i) for i in range(start, min(n, start + wave))]
        flood = loop.time() - t0
        total = sum(n for n, _, _ in attacks.values())

        def mine(s: dict[str, Any]) -> list[dict[str, Any]]:
            return [
                r
                for r in s["audit"]
                if r["from"] == "uav-m" and (r.get("stage"), r.get("code")) in attacks
            ]

        def summed(s: dict[str, Any], key: tuple[str, str]) -> int:
            return sum(r.get("count") or 1 for r in mine(s) if (r["stage"], r["code"]) == key)

        # what is summed up is written at the interval's end: until every refusal is
        s = await w.until_stats(
            "uav-a",
            lambda s: all(summed(s, key) == n for key, (n, _, _) in attacks.items()),
            "every refusal audited, one by one or summed up",
        )
        assert s["gateway"]["unknown_label_refused"] == 1200
        assert s["gateway"]["taken_label_refused"] == 300
        assert s["gateway"]["limit_refused"] == 600
        assert s["refusals"] == {"sharing-rule": 300}
        recs = mine(s)
        one_by_one = [r for r in recs if r.get("count") is None]
        sums = [r for r in recs if r.get("count") is not None]
        for r in one_by_one:
            assert r["verdict"] == "refused" and r["receivers"] is not None, r
            assert r["sender"] in ("mallory@uav-m", "federation@uav-m"), r
            assert r["reason"].startswith(f"{r['code']}: "), r
        # the first of the flood: a budget's worth, each with the whole reason told
        first = one_by_one[:REFUSALS_ONE_BY_ONE]
        assert [r["code"] for r in first] == ["unknown-label"] * REFUSALS_ONE_BY_ONE
        assert all(r["reason"].startswith("unknown-label: unknown label 'probe/") for r in first)
        # at most a budget per platform per interval (each interval starts at a refusal);
        # the flood spans intervals (3 s at least): more than one budget's worth in all
        intervals = int(flood // REFUSAL_AUDIT_INTERVAL) + 1
        assert REFUSALS_ONE_BY_ONE < len(one_by_one) <= REFUSALS_ONE_BY_ONE * intervals, (
            len(one_by_one),
            flood,
        )
        # the rest summed up: per code at most one record an interval (and one at once)
        for (stage, code), (_, _, told) in attacks.items():
            these = [r for r in sums if (r["stage"], r["code"]) == (stage, code)]
            assert these, code
            assert len(these) <= intervals + 1, (code, len(these), flood)
            for r in these:
                assert r["verdict"] == "refused" and r["sender"] is None, r
                assert r["reason"].startswith(
                    f"{code}: {r['count']} more request(s) refused without a record each "
                    f"(over {REFUSALS_ONE_BY_ONE} per {REFUSAL_AUDIT_INTERVAL:g} s of one "
                    "platform), from 'uav-m'"
                ), r
            last = these[-1]["reason"]
            assert last.endswith(")") and "(last: " in last, last
            if code != "unknown-label":  # the same reason each time: the last one's whole
                assert last.endswith(f"(last: {told(0)})"), last
        # a few records a second, whatever the flood's rate: a budget and a summary per
        # code an interval (the first summary may come at once), not one per refusal
        assert len(recs) <= (REFUSALS_ONE_BY_ONE + len(attacks)) * (intervals + 1), (
            len(recs),
            total,
            flood,
        )
        await until(lambda: in_file(tmp_path, "uav-a", recs[-1]), "the record in the audit file")
        lines = (tmp_path / "audit-uav-a.jsonl").read_text().splitlines()
        written = [x for x in lines if json.loads(x) in recs]
        assert len(written) == len(recs)
        # and each under 1 kB (a summary's last reason is cut): a few kB a second in all
        assert max(len(x) for x in written) < 1024, max(written, key=len)
        await held.cancel()


async def test_a_members_words_echoed_in_answers_and_the_audit_are_bounded_on_one_line(
    tmp_path: Path,
) -> None:
    """What a member chose (an ontology, a protocol, a conversation id), echoed in what it
    is answered and in the audit records its messages make, is on one line and bounded
    (`agents.quoted`): one message, however large, cannot forge an audit line nor write a
    record much larger than a fixed size."""
    opened = {"sharing": {"gateway": "protected"}}
    async with (
        asyncio.timeout(120),
        world(tmp_path, ["uav-a"], ["uav-m"], uav_a=opened) as w,
    ):
        m = await mallory(w)
        forged = '\n{"verdict": "accepted", "from": "uav-b"}\x1b[2J'
        big = 20_000
        # an ontology and a protocol no agent has a handler for: answered not-understood
        conv = new_id("c")
        with m.conversation(conv, peers=["federation@uav-a"]) as c:
            await c.send(
                m.message(
                    P.REQUEST,
                    "federation@uav-a",
                    {},
                    ontology="o" + forged + "o" * big,
                    protocol="p" + forged + "p" * big,
                    language="json",
                    conversation_id=conv,
                )
            )
            answer = await c.receive(timeout=WAIT)
        assert answer.performative is P.NOT_UNDERSTOOD
        told = str(answer.content)
        assert told.startswith("federation@uav-a has no handler for request (protocol p\\x0a{")
        assert "\n" not in told and "\x1b" not in told and len(told) < 600
        # a conversation id holding a subscription already: the subscribe is refused
        gw = "gateway@uav-a"
        conv = "c" + forged + "c" * big
        with m.conversation(conv, peers=[gw]) as c:
            sub = m.message(
                P.SUBSCRIBE,
                gw,
                {"label": SECRET},
                ontology="dyknow",
                protocol="fipa-subscribe",
                language="json",
                conversation_id=conv,
            )
            await c.send(sub)
            assert (await c.receive(timeout=WAIT)).performative is P.AGREE
            await c.send(sub)
            while (refused := await c.receive(timeout=WAIT)).performative is P.INFORM:
                pass
            assert refused.performative is P.REFUSE
            told = str(refused.content)
            assert told.startswith("conversation c\\x0a{") and told.endswith(
                "already has a subscription"
            )
            assert "\n" not in told and len(told) < 300
            await c.send(m.message(P.CANCEL, gw, None, ontology="dyknow", conversation_id=conv))
            while (done := await c.receive(timeout=WAIT)).performative is P.INFORM:
                if done.content == "cancelled":
                    break
        s = await w.until_stats(
            "uav-a",
            lambda s: (
                audited(s, stage="delivery", code="not-understood", **{"from": "uav-m"})
                and audited(s, stage="agent-refuse", **{"from": "uav-m"})
            ),
            "the not-understood and the refuse audited",
        )
        for rec in (
            *audited(s, stage="delivery", code="not-understood", **{"from": "uav-m"}),
            *audited(s, stage="agent-refuse", **{"from": "uav-m"}),
        ):
            assert "\n" not in rec["reason"] and "\x1b" not in rec["reason"], rec
            assert len(rec["reason"]) < 800, rec
        (refuse,) = audited(s, stage="agent-refuse", **{"from": "uav-m"})
        assert "gateway@uav-a: conversation c\\x0a{" in refuse["reason"]
        await until(lambda: in_file(tmp_path, "uav-a", refuse), "the record in the audit file")


# -- 2. reply_to -----------------------------------------------------------------------------------


async def test_replies_go_to_the_requesting_platform_only(tmp_path: Path) -> None:
    async with asyncio.timeout(120), world(tmp_path, ["uav-a"], ["uav-b", "uav-m"]) as w:
        b = w.here["uav-b"]
        m = await mallory(w)
        before = b.agents.stats.senders.get("uav-a")
        from_a = 0 if before is None else before.accepted
        n = 20
        conv = new_id("c")
        with m.conversation(conv, peers=["federation@uav-a"]) as c:
            for i in range(n):
                await c.send(
                    m.message(
                        P.REQUEST,
                        "federation@uav-a",
                        {"action": "get-trajectory", "labels": ["car5-state"], "from": -1e9},
                        ontology="dyknow-federation",
                        protocol="fipa-request",
                        language="json",
                        conversation_id=conv,
                        reply_with=f"r-{i}",
                        reply_to=["federation@uav-b"],
                    )
                )
            answers = [await c.receive(timeout=WAIT) for _ in range(n)]
        assert {a.performative for a in answers} == {P.REFUSE}
        assert all(
            "reply_to may name agents of the requesting platform" in str(a.content) for a in answers
        )
        s = await w.stats("uav-a")
        assert s["reply_to_refused"] == n
        await audited_in_file(
            tmp_path,
            s,
            n,
            verdict="refused",
            sender="mallory@uav-m",
            reason="reply_to may name agents",
        )
        await asyncio.sleep(1.0)  # what would have been reflected has had time to arrive
        after = b.agents.stats.senders.get("uav-a")
        assert (0 if after is None else after.accepted) == from_a  # uav-b got nothing


# -- 3. to-units: the receiver's consent ---------------------------------------------------------


async def test_a_stream_goes_to_a_third_platform_only_if_it_agrees(tmp_path: Path) -> None:
    consent = {"sharing": {"accept_for": ["operator"]}}  # uav-b: the operator may direct
    async with (
        asyncio.timeout(150),
        world(tmp_path, ["uav-a", "uav-b"], ["operator", "uav-m"], uav_b=consent) as w,
    ):
        m, op = w.here["uav-m"].federation_agent, w.here["operator"].federation_agent
        reason = await refusal(
            m.create_stream("uav-a", ["car5-state"], to_units=["uav-b"], timeout=WAIT)
        )
        assert reason.startswith("receiver uav-b did not agree to receive ['car5-state']")
        assert "operator asks for it (sharing.accept_for); not for uav-m" in reason
        sa, sb = await w.stats("uav-a"), await w.stats("uav-b")
        assert sa["refusals"] == {"consent": 1} and sb["refusals"] == {"consent": 1}
        (ra,) = audited(sa, verdict="refused", code="consent", sender="federation@uav-m")
        (rb,) = audited(sb, verdict="refused", code="consent", sender="federation@uav-a")
        assert "mallory" not in rb["reason"] and "uav-m" in rb["reason"]
        await until(lambda: in_file(tmp_path, "uav-a", ra), "uav-a's record in its file")
        await until(lambda: in_file(tmp_path, "uav-b", rb), "uav-b's record in its file")
        assert sa["exports"] == [] and sa["agreed"] == {}
        # as a provider, uav-m claims the operator asked it to stream to uav-b: uav-b asks
        # the operator, which did not
        spoof = {"action": "accept-stream", "requester": "operator", "labels": ["car5-state"]}
        reason = await refusal(m.request_from("uav-b", spoof))
        assert reason == (
            "operator did not confirm it asked uav-m for ['car5-state']: federation@operator "
            "refused: operator asked uav-m for no stream of ['car5-state'] to uav-b"
        )
        assert op.refusals == {"consent": 1}
        # nor can uav-b be made to agree in its own name
        direct = {"action": "accept-stream", "requester": "uav-b", "labels": ["car5-state"]}
        reason = await refusal(m.request_from("uav-b", direct))
        assert "asked uav-m for nothing" in reason
        sb = await w.stats("uav-b")
        assert sb["refusals"] == {"consent": 3}
        assert len(audited(sb, verdict="refused", code="consent", sender="federation@uav-m")) == 2
        # the operator may direct uav-a's stream to uav-b: uav-b agrees, and imports it
        await op.create_stream("uav-a", ["car5-state"], to_units=["uav-b"], timeout=WAIT)
        # the paper's flow is unchanged: B asks A for a stream to B itself
        assert (await w.ask("uav-b", "uav-a", ["car6-state"])).startswith("x-")
        sb = await w.until_stats(
            "uav-b",
            lambda s: {"import/uav-a/car5-state", "import/uav-a/car6-state"} <= set(s["labels"]),
            "uav-a's streams imported by uav-b",
        )
        assert sb["refusals"] == {"consent": 3}
        assert not [i for i in sb["imports"]["imports"] if i["sender"] == "uav-m"]


async def test_a_receivers_refusal_quoted_by_the_provider_is_bounded_on_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A member asked to receive a stream refuses with words of its own (a forged line,
    a terminal escape, 20 000 characters): the provider's refusal to the requester and
    its audit record quote them on one line, bounded."""
    async with (
        asyncio.timeout(150),
        world(tmp_path, ["uav-a"], ["operator", "uav-m"]) as w,
    ):
        forged = '\n{"verdict": "accepted", "from": "uav-b"}\x1b[2J' + "w" * 20_000

        async def refuse_in_its_words(req: Any, sender: str) -> dict[str, Any]:
            raise Denied("consent", forged)

        monkeypatch.setattr(w.here["uav-m"].federation_agent, "_accept_stream", refuse_in_its_words)
        op = w.here["operator"].federation_agent
        reason = await refusal(
            op.create_stream("uav-a", ["car5-state"], to_units=["uav-m"], timeout=WAIT)
        )
        assert reason.startswith(
            "receiver uav-m did not agree to receive ['car5-state']: federation@uav-m refused: "
            "\\x0a{"
        )
        assert "\n" not in reason and "\x1b" not in reason and len(reason) < 400
        s = await w.until_stats(
            "uav-a",
            lambda s: audited(s, verdict="refused", code="consent"),
            "the refusal audited",
        )
        (rec,) = audited(s, verdict="refused", code="consent", sender="federation@operator")
        assert rec["reason"] == f"consent: {reason}"
        await until(lambda: in_file(tmp_path, "uav-a", rec), "the record in the audit file")


async def test_a_providers_refusal_of_a_durable_stream_asked_again_is_logged_bounded(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A member asked again for a durable stream refuses in words of its own (a forged
    line, a terminal escape, 20 000 characters): the requester's log line quotes them on
    one line, bounded, as every other platform's words it logs."""
    from types import SimpleNamespace

    from federation._service import FederationAgent, _Durable

    forged = 'no\n{"verdict": "accepted", "from": "uav-b"}\x1b[2J' + "w" * 20_000
    answers: list[Any] = [Refused(f"federation@uav-m refused: {forged}"), {"id": "e2"}]

    async def request_from(provider: str, content: Any) -> Any:
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer

    entry = _Durable({"action": "create-stream", "labels": ["car5-state"]}, "e1")

    class Requester(SimpleNamespace):  # the Federation Agent's state `_ask_one` reads
        def __str__(self) -> str:
            return "federation@operator"

    fa = Requester(_members={"uav-m"}, _durable={"uav-m": {"e1": entry}}, request_from=request_from)
    with caplog.at_level("INFO", logger="federation._service"):
        await asyncio.wait_for(FederationAgent._ask_one(fa, "uav-m", "e1", entry), WAIT)  # type: ignore[arg-type]
    assert entry.current == "e2"
    (line,) = [r.getMessage() for r in caplog.records if "asking uav-m again" in r.getMessage()]
    assert "\n" not in line and "\x1b" not in line and len(line) < 500, line[:300]
    assert line.endswith("left out)"), line[-100:]


# -- 4. unsolicited batches ----------------------------------------------------------------------


async def test_unsolicited_batches_are_dropped_counted_and_audited_boundedly(
    tmp_path: Path,
) -> None:
    n = 2000
    async with asyncio.timeout(150), world(tmp_path, ["uav-b"]) as w:
        m = w.here["uav-m"]
        sessions = InterfaceSessions(m.interface)
        await sessions.ensure("uav-b")
        year_2116 = seconds_to_ns(4_608_000_000)
        prefix = wire_key(w.federation, "stream", "uav-b") + "/uav-m/"

        async def push(first: int) -> dict[str, Any]:
            """n batches of n labels nobody asked for (a sample dated 2116 each); uav-b's stats."""
            for i in range(first, first + n):
                label = f"car{i}-state"
                body = pack_batch(label, [({"forged": i}, year_2116, 0)], 0)
                await m.transport.publish(prefix + label, sessions.seal_bytes("uav-b", body))
                if i % 100 == 0:
                    await asyncio.sleep(0.01)
            return await w.until_stats(
                "uav-b",
                lambda s: (
                    s["imports"]["totals"]["dropped_samples"].get("unagreed", 0) >= first + n
                    and sum(r.get("count", 0) for r in audited(s, stage="import")) >= first + n
                ),
                "every batch counted and summed up in the audit",
            )

        # uav-b's own streams keep up to 10 000 samples each (the default cache): ~40 streams
        # at 20 Hz grow its RSS by ~200 kB a second whatever arrives, more the longer a flood
        # takes on a busy machine. Stopped, what grows between the floods is the flood's.
        w.pipes["uav-b"].send("quiet")
        await w.pipes["uav-b"].expect("quiet", WAIT)
        # the first flood warms up what any traffic grows (transport buffers, allocator)
        s = await push(0)
        assert s["imports"]["totals"]["dropped_samples"]["unagreed"] == n
        assert s["imports"]["totals"]["injected"] == 0
        assert not [lb for lb in s["labels"] if lb.startswith("import/uav-m")]
        assert "import/uav-m" not in s["locations"]
        assert s["imports"]["imports"] == []  # no import agreed, none made by the flood
        # their counters are bounded too: 64 by label, then one bucket for the rest
        assert len(s["imports"]["strays"]) <= 65
        recs = audited(s, verdict="dropped", stage="import", code="unagreed", **{"from": "uav-m"})
        assert sum(r["count"] for r in recs) == n
        assert len(recs) <= 20, len(recs)  # summed up, not one record per batch
        assert recs[0]["reason"].startswith("unagreed: ")
        await until(lambda: in_file(tmp_path, "uav-b", recs[-1]), "the record in the audit file")
        # a second flood of as many new labels costs (next to) nothing more
        s2 = await push(n)
        assert s2["imports"]["totals"]["dropped_samples"]["unagreed"] == 2 * n
        assert len(s2["imports"]["strays"]) <= 65 and s2["imports"]["imports"] == []
        grew = s2["rss_kb"] - s["rss_kb"]
        print(f"AUTHZ unsolicited: {n} more labels pushed, RSS of uav-b grew {grew} kB")
        assert grew < 2 * 1024, grew


# -- 5. export slots per requesting platform ----------------------------------------------------


async def test_one_member_cannot_take_every_export_slot(tmp_path: Path) -> None:
    limits = {"export_limit": 12, "export_limit_per_platform": 8, "history_limit_per_platform": 500}
    async with (
        asyncio.timeout(150),
        world(tmp_path, ["uav-a"], ["uav-c", "uav-m"], uav_a=limits) as w,
    ):
        fed = w.here["uav-m"].federation_agent
        for i in range(8):
            await fed.create_stream("uav-a", [f"car{i}-state"], timeout=WAIT)
        reason = await refusal(fed.create_stream("uav-a", ["car8-state"], timeout=WAIT))
        assert reason == (
            "too many exports for uav-m (export_limit_per_platform 8: 8 running, 1 asked)"
        )
        # the others are still served
        await w.here["uav-c"].federation_agent.create_stream("uav-a", ["car8-state"], timeout=WAIT)
        # history: bounded per requesting platform too (here 500 samples)
        other = w.here["uav-c"].federation_agent
        reason = await refusal(other.create_stream("uav-a", ["car9-state"], history=501))
        assert reason == (
            "too much history for uav-c (history_limit_per_platform 500 samples: 0 kept, 501 asked)"
        )
        s = await w.stats("uav-a")
        assert s["refusals"] == {"export-limit": 1, "history-limit": 1}
        (rm,) = audited(s, code="export-limit", sender="federation@uav-m")
        (rc,) = audited(s, code="history-limit", sender="federation@uav-c")
        assert rm["verdict"] == rc["verdict"] == "refused"
        await until(lambda: in_file(tmp_path, "uav-a", rc), "the record in the audit file")
        by = {}
        for e in s["agreed"].values():
            by[e["requester"]] = by.get(e["requester"], 0) + len(e["labels"])
        assert by == {"federation@uav-m": 8, "federation@uav-c": 1}


# -- 7. sharing rules ------------------------------------------------------------------------------


RULES = {
    "sharing": {
        "default": "none",
        "rules": [
            {
                "name": "neighbours",
                "labels": ["car*-state"],
                "query": ["uav-c", "uav-b"],
                "stream": ["uav-b"],
            }
        ],
    }
}


async def test_sharing_rules_say_who_may_query_or_stream_which_label(tmp_path: Path) -> None:
    async with (
        asyncio.timeout(120),
        world(tmp_path, ["uav-a"], ["uav-c", "uav-m"], uav_a=RULES) as w,
    ):
        m, c = w.here["uav-m"].federation_agent, w.here["uav-c"].federation_agent
        latest = {"action": "get-latest", "labels": ["car5-state"]}
        reason = await refusal(m.request_from("uav-a", latest))
        assert reason == (
            "label 'car5-state' may not be queried by uav-m: sharing rule 'neighbours' "
            "(sharing.rules[0]) (car*-state) lets uav-c, uav-b query it"
        )
        reason = await refusal(m.create_stream("uav-a", ["car5-state"], timeout=WAIT))
        assert "may not be streamed to uav-m: sharing rule 'neighbours'" in reason
        altitude = {"action": "get-latest", "labels": ["heli-altitude"]}
        reason = await refusal(m.request_from("uav-a", altitude))
        assert reason.endswith('no sharing rule names it and sharing.default is "none"')
        assert await m.request_from("uav-a", {"action": "list-labels"}) == {"labels": []}
        # a neighbour may query, but not stream
        answer = await c.request_from("uav-a", latest)
        assert isinstance(answer, dict) and answer["car5-state"]["samples"]
        reason = await refusal(c.create_stream("uav-a", ["car5-state"], timeout=WAIT))
        assert "lets uav-b stream it" in reason
        s = await w.stats("uav-a")
        assert s["at_once"]["federation"] == 1  # the neighbour's read; no refusal was
        assert s["refusals"] == {"sharing-rule": 4}
        recs = audited(s, verdict="refused", code="sharing-rule")
        assert [r["from"] for r in recs] == ["uav-m", "uav-m", "uav-m", "uav-c"]
        await until(lambda: in_file(tmp_path, "uav-a", recs[-1]), "the record in the audit file")


def test_a_refused_consent_says_who_may_direct_streams_here() -> None:
    # the default names nobody: the reason must not read as if nobody asking sufficed
    default = SharingSettings().sharing().accepts_for("uav-m")
    assert default == (
        "this platform receives streams only when it asks for them "
        "(sharing.accept_for names no other platform); not for uav-m"
    )
    named = SharingSettings(accept_for=["operator", "ops-*"]).sharing()
    assert named.accepts_for("ops-2") is None
    assert "or when operator, ops-* asks for it (sharing.accept_for)" in str(
        named.accepts_for("uav-m")
    )


def test_sharing_settings_are_validated_with_file_and_key(tmp_path: Path) -> None:
    base = {"name": "a", "federation": "f", "key": "k", "trust": "t"}
    base |= {"vocabulary": {}, "mapping": {}}
    ok = PlatformConfig.from_dict({**base, **RULES})
    assert ok.sharing.rules[0].name == "neighbours" and ok.sharing.gateway == "private"
    assert PlatformConfig.from_dict(base).sharing.default == "members"
    bad = [
        ({"sharing": {"rules": [{"lables": ["x"]}]}}, r"sharing\.rules\[0\]\.labels: missing"),
        ({"sharing": {"gateway": "public"}}, r"sharing\.gateway: Input should be 'private'"),
        ({"sharing": {"accept_for": ["uav b"]}}, r"sharing\.accept_for\[0\]: 'uav b': use"),
        ({"sharing": {"rules": [{"labels": []}]}}, r"sharing\.rules\[0\]\.labels"),
        ({"export_limit_per_platform": -1}, r"export_limit_per_platform"),
    ]
    for more, message in bad:
        path = tmp_path / "p.toml"
        with pytest.raises(PlatformConfigError, match=message) as info:
            PlatformConfig.from_dict({**base, **more}, source=str(path))
        assert str(info.value).startswith(f"{path}: ")


async def test_a_sharing_pattern_no_trusted_platform_matches_is_warned_on_joining(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A misspelt platform in [sharing] lets no one in, silently: joining names it, once.
    A platform opened only to ask (every one-shot command) says nothing of it."""
    pubs = [gen_keys(n, tmp_path / "keys")[2] for n in ("roadside", "tmc")]
    trust_keys(tmp_path / "trust.json", pubs, federation="f")
    rules = [{"labels": ["*-speed"], "query": ["tmc", "ops-*"], "stream": ["tcm"]}]
    config = PlatformConfig.from_dict(
        {
            "name": "roadside",
            "federation": "f",
            "key": str(tmp_path / "keys" / "roadside.key"),
            "trust": str(tmp_path / "trust.json"),
            "vocabulary": VOCABULARY,
            "mapping": {"vocabulary": "traffic", "labels": MAPPING},
            "sharing": {"default": "none", "accept_for": ["*"], "rules": rules},
        }
    )
    hub = MemoryHub()

    def said() -> list[str]:
        return [r.getMessage() for r in caplog.records if r.name == "federation._platform"]

    @contextlib.asynccontextmanager
    async def opened(join: bool) -> AsyncIterator[FederationPlatform]:
        async with (
            hub.transport() as transport,
            FederationPlatform(config, source="roadside.toml", join=join, transport=transport) as p,
        ):
            yield p

    with caplog.at_level("WARNING", logger="federation._platform"):
        async with opened(join=False):  # as `dyknow ask` opens it
            pass
        assert said() == []
        async with opened(join=False) as node:  # as `dyknow node` does, then joins
            await node.join()
            await node.join()
        warned = said()
        async with opened(join=True):
            pass
        assert said() == warned * 2
    known = f"names no platform of the trust file {tmp_path / 'trust.json'} (roadside, tmc)"
    assert warned == [
        f"roadside.toml: sharing.rules[0].query[1]: 'ops-*' {known}: it lets no one in",
        f"roadside.toml: sharing.rules[0].stream[0]: 'tcm' {known}: it lets no one in",
    ]


async def test_drops_under_invented_sender_names_are_audited_in_bounded_records() -> None:
    # an outsider need not authenticate to invent senders: one record each would be a flood.
    # The budget is per report: 32 senders by name, then one "*" for the rest. A busy
    # machine may spread the flood over several reports, but never more than one an interval
    interval = 0.2
    loop = asyncio.get_running_loop()
    reports: list[list[tuple[str, str, int, int]]] = []
    telling: list[bool] = []  # non-empty while one report's records are being told

    def told(sender: str, reason: str, batches: int, samples: int) -> None:
        # a report tells all its records in one go, never awaiting in between: the first
        # opens an entry, closed as soon as the event loop gets back to its callbacks
        if not telling:
            telling.append(True)
            loop.call_soon(telling.clear)
            reports.append([])
        reports[-1].append((sender, reason, batches, samples))

    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        await net.platform("uav-b")
        raw = await stack.enter_async_context(net.hub.transport())
        imp = await net.importer(
            "uav-b",
            PlainSessions("uav-b", trusted={"uav-a"}),
            translate=lambda sender, semantic: None,
            on_refused=told,
            report_interval=interval,
        )
        n = 1000
        start = loop.time()
        for i in range(n):
            envelope = PlainSessions(f"x{i}").seal_bytes("uav-b", pack_batch("car5-state", []))
            await raw.publish(stream_key("uav-b", f"x{i}", "car5-state"), envelope)
        await until(lambda: sum(t[2] for r in reports for t in r) == n, "every batch summed up")
        elapsed = loop.time() - start
        # each report waits a whole interval after the drop that made it due
        assert len(reports) <= elapsed / interval + 1, (len(reports), elapsed)
        for report in reports:
            assert len(report) <= 33, len(report)  # 32 senders by name, then one "*"
            assert len({t[0] for t in report}) == len(report)  # one record per sender
        records = [t for r in reports for t in r]
        assert {t[1] for t in records} == {"untrusted"}
        assert ("*", "untrusted") in {(t[0], t[1]) for t in records}
        assert imp.stats()["totals"]["dropped_batches"] == {"untrusted": n}


async def test_a_members_refusal_to_cancel_a_one_shot_commands_stream_is_logged_bounded(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The last local command following a member's stream ends; the member refuses the
    cancel in words of its own (a forged line, a terminal escape, 20 000 characters): the
    local channel's log line quotes them on one line, bounded (docs/security.md)."""
    from types import SimpleNamespace

    from federation._local import LocalChannel, _Shared

    forged = 'no\n{"verdict": "accepted", "from": "uav-b"}\x1b[2J' + "w" * 20_000

    async def cancel_stream(target: str, export_id: str, timeout: float) -> None:
        raise Refused(f"federation@{target} refused: {forged}")

    entry = _Shared("e1", ("uav-m", "car5-state"), None)
    channel = SimpleNamespace(
        _lock=asyncio.Lock(),
        _exports={entry.key: entry},
        _pending={},
        platform=SimpleNamespace(federation_agent=SimpleNamespace(cancel_stream=cancel_stream)),
    )
    with caplog.at_level("INFO", logger="federation._local"):
        await asyncio.wait_for(LocalChannel._release(channel, "uav-m", entry), WAIT)  # type: ignore[arg-type]
    assert channel._exports == {} and channel._pending == {}
    (line,) = [r.getMessage() for r in caplog.records if "cancelling the export" in r.getMessage()]
    assert "\n" not in line and "\x1b" not in line and len(line) < 500, line[:300]
    assert line.endswith("left out)"), line[-100:]
