"""A platform's close ends even when one of its tasks lost the cancellation it was sent.

Python 3.11's ``asyncio.wait_for`` returns a result that comes in the same turn as a
cancellation of the waiting task and drops the cancellation; code may also swallow one
by mistake. Such a task ran on after its owner's close cancelled it, and the close (a
task group's exit) waited for it forever: a CI run hung so. The platform and its agents
now cancel again, every `RECANCEL_AFTER` s, what outlived its cancellation.
"""

from __future__ import annotations

import asyncio
import time

import pytest

from agents import Agent, AgentPlatform, MemoryHub
from agents._aio import KeepCancelled
from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port

AFTER = 0.2  # s: the re-cancel interval in these tests (the default, 5 s, is for cleanups)
CLEANUP = 0.05  # s: a cancelled task's cleanup
WAIT = 10.0  # s: the bound on a close that ends; without the re-cancel it never does


async def loses_one_cancellation(lost: list[str], name: str) -> None:
    """Wait forever; the first cancellation is lost, as 3.11's wait_for loses one."""
    try:
        await asyncio.Event().wait()
    except asyncio.CancelledError:
        lost.append(name)  # and on, as if the answer had come with it
    await asyncio.Event().wait()


@pytest.fixture(autouse=True)
def _short_interval(monkeypatch: pytest.MonkeyPatch) -> None:
    """Re-cancel after `AFTER` s here: the tests' closes then take a fraction of a second."""
    monkeypatch.setattr("agents._aio.RECANCEL_AFTER", AFTER)
    monkeypatch.setattr(KeepCancelled.__init__, "__defaults__", (AFTER,))


async def test_a_platform_task_that_lost_its_cancellation_does_not_hold_the_close() -> None:
    """A task the platform owns loses the close's cancellation: cancelled again, it ends."""
    lost: list[str] = []
    async with asyncio.timeout(WAIT), MemoryHub().transport() as t:
        platform = AgentPlatform("p", t, federation=f"lost-{time.monotonic_ns()}")
        async with platform:
            task = platform.spawn(loses_one_cancellation(lost, "platform"), "loser")
            await asyncio.sleep(0)  # it waits
        assert lost == ["platform"]
        assert task.cancelled()
        assert not platform.running


async def test_an_agents_task_that_lost_its_cancellation_does_not_hold_its_stop() -> None:
    """An agent's task loses the stop's cancellation: the agent still stops, the platform closes."""
    lost: list[str] = []
    async with asyncio.timeout(WAIT), MemoryHub().transport() as t:
        platform = AgentPlatform("p", t, federation=f"lost-{time.monotonic_ns()}")
        async with platform:
            agent = await platform.add(Agent("a"))
            task = agent.spawn(loses_one_cancellation(lost, "agent"), "loser")
            await asyncio.sleep(0)
            await agent.stop()
            assert lost == ["agent"]
            assert task.done()
            loser = platform.spawn(loses_one_cancellation(lost, "at close"), "loser")
            await asyncio.sleep(0)
        assert lost == ["agent", "at close"]
        assert loser.cancelled()


async def test_a_task_given_time_for_its_cleanup_is_cancelled_again_only_after_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A cancelled task's cleanup runs `RECANCEL_AFTER` s before a second cancellation."""
    # far longer than the cleanup: only a loop stalled for seconds could interrupt it
    monkeypatch.setattr(KeepCancelled.__init__, "__defaults__", (CLEANUP * 40,))
    cleaned: list[float] = []

    async def cleans_up() -> None:
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            started = time.monotonic()
            await asyncio.sleep(CLEANUP)  # a short cleanup: not interrupted
            cleaned.append(time.monotonic() - started)
            raise

    async with asyncio.timeout(WAIT), MemoryHub().transport() as t:
        platform = AgentPlatform("p", t, federation=f"lost-{time.monotonic_ns()}")
        async with platform:
            task = platform.spawn(cleans_up(), "cleaner")
            await asyncio.sleep(0)
        assert len(cleaned) == 1 and task.cancelled()


async def test_a_transport_task_that_lost_its_cancellation_does_not_hold_its_close() -> None:
    """A transport's own task (a reader, an unsubscribe) losing one cancellation: it closes."""
    lost: list[str] = []
    async with asyncio.timeout(WAIT):
        t = ZenohTransport(ZenohConfig.loopback(free_tcp_port()))
        async with t:
            task = t._spawn(loses_one_cancellation(lost, "transport"), "loser")
            await asyncio.sleep(0)
        assert lost == ["transport"]
        assert task.cancelled()
