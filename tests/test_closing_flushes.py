"""What is counted and summed up for later is written when its owner closes, not lost.

- `Tally.close`: the owner's last flush; a flush armed before it is cancelled, and what
  is added after is counted only (it armed a flush on a loop about to close, and the
  tally stayed "scheduled" for good);
- the global directory's presence changes counted but not yet audited, and its event
  gate's summary due within the interval, are written at its close;
- the import proxy tells ``on_refused`` what it refused since its last report;
- a refusal for an agent that is stopping is counted (`PlatformStats.stopping`);
- a member's refusals past its one-by-one budget (`AgentPlatform.audit_refused`) are
  summed up, the last ones at the platform's close;
- a snapshot that raises does not leave the name alive (nor exempt) for good;
- ``runs_signed`` keeps a bounded number of the refused answers it hands back.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Hashable
from typing import Any

import pytest
from _victim import members

from agents import Agent, AgentPlatform, InterfaceAgent, KeyPair, TrustStore, runs_signed, wire_key
from agents._acl import ACLMessage, Performative
from agents._agent import _STOPPING
from agents._df import RUNS_REFUSED_KEPT
from agents._platform import REFUSALS_ONE_BY_ONE
from agents._tally import Tally
from agents.transports import MemoryHub
from dyknow_core import DyKnowInstance
from federation import ImportProxy, InterfaceSessions

FED = "closing"


async def test_a_closed_tally_flushes_once_and_arms_nothing_after() -> None:
    got: list[tuple[Hashable, int]] = []
    tally = Tally(lambda key, n, detail, seconds: got.append((key, n)), interval=0.5)
    tally.bind(asyncio.get_running_loop())
    tally.add("a", "x")
    await asyncio.sleep(0.01)  # the first: at once
    tally.add("a", "y")
    await asyncio.sleep(0.01)  # within the interval: a flush armed for later
    tally.close()
    assert got == [("a", 1), ("a", 1)]
    # from another thread, after the close: counted, never emitted, nothing armed
    adder = threading.Thread(target=lambda: [tally.add(f"k{i}", "z") for i in range(3)])
    adder.start()
    adder.join()
    await asyncio.sleep(0.7)  # past the interval the flush was armed for
    assert got == [("a", 1), ("a", 1)]
    assert tally.pending == 3 and not tally._scheduled


def _records(platform: AgentPlatform, stage: str) -> list[dict[str, Any]]:
    channel = platform.channel
    assert isinstance(channel, InterfaceAgent)
    return [r for r in channel.audit.records if r.get("stage") == stage]


async def test_the_global_directorys_counts_are_audited_at_its_close() -> None:
    """Presence changes dropped from a full queue, events shed just now: in the audit."""
    async with asyncio.timeout(10), members(FED, "uav-a") as [pa]:
        view = pa.global_df
        assert view is not None and view.event_gate is not None
        gate = view.event_gate
        assert not gate.admit(b"junk")  # summed up at once (the first)
        while not _records(pa, "df-events-shed"):  # noqa: ASYNC110
            await asyncio.sleep(0.01)
        for _ in range(3):
            assert not gate.admit(b"junk")  # within the interval: for the next summary
        view._presence_limit("uav-b", 7)  # as a full queue of raw changes does
    shed = _records(pa, "df-events-shed")
    assert sum(r["count"] for r in shed) == gate.shed_total == 4, shed
    limited = _records(pa, "df-presence-limited")
    assert [(r["from"], r["count"]) for r in limited] == [("uav-b", 7)], limited
    assert "closed before acting" in limited[0]["reason"]


async def test_a_message_for_an_agent_that_is_stopping_is_counted() -> None:
    async with asyncio.timeout(10), members(FED, "uav-a") as [pa]:
        agent = await pa.add(Agent("slow"))
        agent._state = _STOPPING  # as while it stops
        message = ACLMessage(  # an answer itself: the platform answers nothing
            performative=Performative.FAILURE, sender="x@uav-b", receivers=["slow@uav-a"]
        )
        await pa._local("slow@uav-a", message)
        assert pa.stats.stopping == 1


async def test_refusals_past_a_platforms_budget_are_summed_up_and_written_at_close(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A member's refusals past its one-by-one budget: summed up (the first at once, the
    next at the interval's end or, as here, at the platform's close)."""
    # an interval no stall of a loaded machine outlasts: the refusals below are all in one
    monkeypatch.setattr("agents._platform.REFUSAL_AUDIT_INTERVAL", 3600.0)
    async with asyncio.timeout(10), members(FED, "uav-a") as [pa]:
        asked = ACLMessage(
            performative=Performative.REQUEST, sender="m@uav-b", receivers=["gateway@uav-a"]
        )
        told = [f"unknown label 'probe/{i}'" for i in range(REFUSALS_ONE_BY_ONE + 2)]
        written = [pa.audit_refused(asked, "gateway", "unknown-label", r) for r in told[:-1]]
        assert written == [True] * REFUSALS_ONE_BY_ONE + [False]
        while not [r for r in _records(pa, "gateway") if r.get("count")]:  # noqa: ASYNC110
            await asyncio.sleep(0.01)  # the summary's first record after a quiet spell
        # within the interval: for the summary's next record, due after the close
        assert not pa.audit_refused(asked, "gateway", "unknown-label", told[-1])
        # this platform's own agents' refusals are not budgeted
        own = asked.model_copy(update={"sender": "a@uav-a"})
        assert pa.audit_refused(own, "gateway", "stream-limit", "too many created streams")
    recs = [r for r in _records(pa, "gateway") if r["from"] == "uav-b"]
    one_by_one = [r for r in recs if r.get("count") is None]
    assert [r["reason"] for r in one_by_one] == [
        f"unknown-label: {r}" for r in told[:REFUSALS_ONE_BY_ONE]
    ]
    assert all(r["sender"] == "m@uav-b" and r["performative"] == "request" for r in one_by_one)
    summed = [(r.get("count"), r["reason"]) for r in recs if r.get("count") is not None]
    head = (
        f"unknown-label: 1 more request(s) refused without a record each (over "
        f"{REFUSALS_ONE_BY_ONE} per 3600 s of one platform), from 'uav-b'"
    )
    assert summed[0] == (1, f"{head} (last: {told[-2]})"), summed
    assert summed[1][0] == 1 and summed[1][1].startswith(f"{head} in "), summed
    assert summed[1][1].endswith(f" s (last: {told[-1]})"), summed
    assert len(summed) == 2


async def test_a_snapshot_that_raises_leaves_no_name_alive() -> None:
    """A fault (not an unanswered query) while taking uav-b's snapshot: it is not alive."""
    async with asyncio.timeout(10), members(FED, "uav-a", "uav-b") as [pa, _]:
        view = pa.global_df
        assert view is not None and view.event_gate is not None
        while "uav-b" not in view.platforms:  # noqa: ASYNC110
            await asyncio.sleep(0.01)
        view._gone("uav-b")  # as if it had left; its presence comes again

        async def broken(platform: str) -> bool:
            raise RuntimeError("a bug")

        view._fetch = broken  # type: ignore[method-assign]
        await view._on_presence("uav-b", True)
        assert "uav-b" not in view._alive
        assert "uav-b" not in view.event_gate.priority | view.event_gate.joining


async def test_the_import_proxy_tells_its_refusals_when_it_closes() -> None:
    """A batch refused within the report interval is told to ``on_refused`` at the close."""
    hub = MemoryHub()
    keys = KeyPair.generate("uav-v")
    channel = InterfaceAgent(keys, TrustStore(FED, {"uav-v": keys.public_key}))
    told: list[tuple[str, str, int, int]] = []
    async with (
        asyncio.timeout(10),
        hub.transport() as tv,
        hub.transport() as tx,
        DyKnowInstance("uav-v") as dk,
    ):
        importer = ImportProxy(
            "uav-v",
            FED,
            tv,
            dk,
            InterfaceSessions(channel),
            lambda sender, semantic: None,
            on_refused=lambda *args: told.append(args),
            report_interval=30.0,  # no report before the close
        )
        async with importer:
            await tx.publish(wire_key(FED, "stream", "uav-v") + "/evil", b"junk")
            while not importer.stats()["totals"]["dropped_batches"]:  # noqa: ASYNC110
                await asyncio.sleep(0.01)
            assert told == []
        assert told == [("evil", "malformed", 1, 0)]


async def test_runs_signed_hands_back_a_bounded_number_of_refused_answers(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Every answer in uav-x's name is junk: counted, the first few handed back, one line."""
    hub = MemoryHub()
    keys = {n: KeyPair.generate(n) for n in ("uav-x", "uav-y")}
    trust = TrustStore(FED, {n: k.public_key for n, k in keys.items()})
    tries = RUNS_REFUSED_KEPT + 8

    async def junk(key: str, payload: bytes) -> bytes:
        return b"junk"

    refused: list[tuple[str | None, str]] = []
    async with asyncio.timeout(10), hub.transport() as tx, hub.transport() as ty:
        await tx.serve(wire_key(FED, "df", "uav-x"), junk)
        with caplog.at_level(logging.WARNING, logger="agents._df"):
            runs = await runs_signed(
                ty, keys["uav-y"], trust, "uav-x", timeout=0.5, tries=tries, refused=refused
            )
    assert runs is False
    assert len(refused) == RUNS_REFUSED_KEPT
    lines = [r.getMessage() for r in caplog.records if "runs" in r.getMessage()]
    assert len(lines) == 1 and f"{tries} directory answer(s)" in lines[0], lines
