"""One timer for the deadlines of a loop's waits (`Deadlines`): each wait still ends at its
own deadline, in deadline order, an item before it wins, a cancelled wait harms none, the
waits that ended do not pile up; and an agent's conversations wait that way."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable, Coroutine
from typing import Any

import pytest
import uvloop

import agents
from agents import ACLMessage, Agent, Deadlines, Mailbox, MessageTemplate, ReplyTimeout, new_id
from agents._aio import _COMPACT_AT
from tests.test_agents import P, Recorder, _keep, msg, platforms

# uvloop rounds a timer's delay to the millisecond: a timer may fire up to that early
SLACK = 0.002


def _on(loop_name: str, main: Callable[[], Coroutine[Any, Any, None]]) -> None:
    (uvloop.run if loop_name == "uvloop" else asyncio.run)(main())


@pytest.mark.parametrize("loop_name", ["asyncio", "uvloop"])
def test_each_wait_ends_at_its_own_deadline_in_deadline_order(loop_name: str) -> None:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        deadlines = Deadlines(loop)
        ended: list[tuple[str, float]] = []
        start = loop.time()

        async def wait(name: str, box: Mailbox[int], after: float) -> int | None:
            deadline = start + after
            try:
                return await box.get(deadline, loop=loop, deadlines=deadlines)
            except TimeoutError:
                ended.append((name, loop.time()))
                assert loop.time() >= deadline - SLACK, f"{name} ended before its deadline"
                return None

        answered: Mailbox[int] = Mailbox(4)
        # added latest first: each earlier one re-arms the one timer
        waits = [
            asyncio.create_task(wait("late", Mailbox(4), 0.15)),
            asyncio.create_task(wait("answered", answered, 0.12)),
            asyncio.create_task(wait("middle", Mailbox(4), 0.10)),
            asyncio.create_task(wait("early", Mailbox(4), 0.05)),
        ]
        loop.call_later(0.02, answered.put, 7)
        got = await asyncio.wait_for(asyncio.gather(*waits), 5.0)
        assert got == [None, 7, None, None]
        assert [name for name, _ in ended] == ["early", "middle", "late"]
        assert ended[-1][1] - start < 1.0  # none waited for long past its deadline
        assert len(deadlines) == 0  # the timer left no entry behind once all had ended

    _on(loop_name, main)


@pytest.mark.parametrize("loop_name", ["asyncio", "uvloop"])
def test_waits_whose_deadlines_passed_together_end_in_deadline_order(loop_name: str) -> None:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        deadlines = Deadlines(loop)
        ended: list[float] = []
        start = loop.time()

        async def wait(after: float) -> None:
            with pytest.raises(TimeoutError):
                await Mailbox[int](4).get(start + after, loop=loop, deadlines=deadlines)
            ended.append(after)

        waits = [asyncio.create_task(wait(after)) for after in (0.03, 0.01, 0.02)]
        await asyncio.sleep(0)  # each waits now
        # the loop kept busy past all three deadlines (blocking on purpose): one timer ends all
        time.sleep(0.05)  # noqa: ASYNC251
        await asyncio.wait_for(asyncio.gather(*waits), 5.0)
        assert ended == [0.01, 0.02, 0.03]

    _on(loop_name, main)


@pytest.mark.parametrize("loop_name", ["asyncio", "uvloop"])
def test_a_deadline_already_past_ends_the_wait_on_the_next_turn(loop_name: str) -> None:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        deadlines = Deadlines(loop)
        queued: Mailbox[int] = Mailbox(4)
        queued.put(1)
        assert await queued.get(loop.time() - 1.0, loop=loop, deadlines=deadlines) == 1
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(
                Mailbox[int](4).get(loop.time() - 1.0, loop=loop, deadlines=deadlines), 5.0
            )

    _on(loop_name, main)


@pytest.mark.parametrize("loop_name", ["asyncio", "uvloop"])
def test_a_cancelled_wait_leaves_the_others_to_their_deadlines(loop_name: str) -> None:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        deadlines = Deadlines(loop)
        start = loop.time()
        cancelled = asyncio.create_task(
            Mailbox[int](4).get(start + 0.03, loop=loop, deadlines=deadlines)
        )
        other = Mailbox[int](4)
        waiting = asyncio.create_task(other.get(start + 0.06, loop=loop, deadlines=deadlines))
        await asyncio.sleep(0)
        cancelled.cancel()
        with pytest.raises(asyncio.CancelledError):
            await cancelled
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(waiting, 5.0)
        assert loop.time() >= start + 0.06 - SLACK
        assert other._waiter is None

    _on(loop_name, main)


async def test_code_around_the_agents_keeps_its_mailboxes_deadlines_on_one_timer() -> None:
    """`Deadlines` is public with `Mailbox`: consumers of several mailboxes (as an agent's
    conversations) share one loop timer, and each wait still ends at its own deadline."""
    assert "Deadlines" in agents.__all__ and agents.Deadlines is Deadlines
    loop = asyncio.get_running_loop()
    deadlines = agents.Deadlines(loop)
    boxes = [agents.Mailbox[int](4) for _ in range(3)]
    afters = (0.06, 0.02, 0.04)
    start = loop.time()

    async def wait(box: Mailbox[int], after: float) -> float:
        with pytest.raises(TimeoutError):
            await box.get(start + after, deadlines=deadlines)
        return loop.time() - start

    async with asyncio.timeout(10):
        took = await asyncio.gather(*map(wait, boxes, afters))
    assert took[1] <= took[2] <= took[0]
    assert all(after >= a - SLACK for after, a in zip(took, afters, strict=True))
    assert len(deadlines) == 0  # each wait's entry dropped at its deadline


async def test_waits_that_ended_early_do_not_pile_up() -> None:
    loop = asyncio.get_running_loop()
    deadlines = Deadlines(loop)
    box: Mailbox[int] = Mailbox(4)
    far = loop.time() + 3600.0  # never reached in the test: only the compaction drops these
    for i in range(5 * _COMPACT_AT):
        loop.call_soon(box.put, i)
        assert await box.get(far, loop=loop, deadlines=deadlines) == i
    assert len(deadlines) <= _COMPACT_AT
    # the timer still ends a wait at its deadline after all those
    start = loop.time()
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(box.get(start + 0.03, loop=loop, deadlines=deadlines), 5.0)
    assert loop.time() >= start + 0.03 - SLACK


async def test_a_timer_drops_the_many_waits_that_ended_before_it_and_the_rest_still_end() -> None:
    """Past a share of the heap, the ended waits in front of the next wait still waiting go
    in one pass (not a pop each): the waits still waiting keep their deadlines and order."""
    loop = asyncio.get_running_loop()
    deadlines = Deadlines(loop)
    start = loop.time()
    ended: list[tuple[int, float]] = []
    # the first timer may run late on a loaded machine: the later waits (and the ended ones
    # in front of them) are far enough from it that it still finds them not yet due
    afters = (0.33, 0.30, 0.03)

    async def wait(k: int) -> None:
        with pytest.raises(TimeoutError):
            await Mailbox[int](4).get(start + afters[k], loop=loop, deadlines=deadlines)
        ended.append((k, loop.time()))

    waits = [asyncio.create_task(wait(k)) for k in range(3)]
    await asyncio.sleep(0)  # each wait added its deadline
    for i in range(300):  # answered at once: deadlines between the first wait's and the next
        waiter: asyncio.Future[None] = loop.create_future()
        deadlines.add(start + 0.25 + i * 1e-5, waiter)
        waiter.set_result(None)
    assert len(deadlines) == 303
    await asyncio.wait_for(waits[2], 5.0)
    assert ended == [(2, ended[0][1])]
    assert len(deadlines) == 2  # the first timer dropped every ended wait before the next
    await asyncio.wait_for(asyncio.gather(*waits), 5.0)
    assert [k for k, _ in ended] == [2, 1, 0]
    for k, at in ended:
        assert at >= start + afters[k] - SLACK
    assert len(deadlines) == 0


async def test_an_agents_conversations_time_out_at_their_deadlines_on_one_timer() -> None:
    async with asyncio.timeout(10), platforms("p") as [p]:
        sleeper = await p.add(Recorder("sleeper"))
        sleeper.add_handler(MessageTemplate(P.REQUEST), _keep(sleeper, "req"))  # never answers
        asker = await p.add(Agent("asker"))
        deadlines = asker._deadlines
        assert deadlines is not None
        loop = asyncio.get_running_loop()
        start = loop.time()

        async def ask(timeout: float) -> float:
            with pytest.raises(ReplyTimeout):
                await asker.ask(msg(asker, sleeper.aid, P.REQUEST), timeout=timeout)
            return loop.time() - start

        took = await asyncio.gather(ask(0.12), ask(0.04), ask(0.08))
        for timeout, after in zip((0.12, 0.04, 0.08), took, strict=True):
            assert timeout - SLACK <= after < timeout + 2.0
        assert took[1] <= took[2] <= took[0]
        assert not asker._by_conv and not asker._by_reply  # each conversation closed
        assert len(deadlines) == 0
    assert asker._deadlines is None  # stopped: it waits on no loop any more


async def test_a_timeout_does_not_look_at_every_wait_still_far_from_its_deadline() -> None:
    loop = asyncio.get_running_loop()
    deadlines = Deadlines(loop)
    looked = 0

    class Far(asyncio.Future[None]):
        def done(self) -> bool:
            nonlocal looked
            looked += 1
            return super().done()

    # many waits far from their deadlines (an agent asking with long timeouts)
    far = [Far(loop=loop) for _ in range(2000)]
    for i, waiter in enumerate(far):
        deadlines.add(loop.time() + 3600.0 + i, waiter)
    looked = 0  # adding them compacted the heap once: that looked at each, and is done
    timeouts = 50
    for _ in range(timeouts):
        start = loop.time()
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(
                Mailbox[int](4).get(start + 0.001, loop=loop, deadlines=deadlines), 5.0
            )
    # each timer looks at the next wait at most, not at all of them (a stalled loop)
    assert looked <= 4 * timeouts
    assert not any(waiter.done() for waiter in far)
    for waiter in far:
        waiter.cancel()


async def test_a_deadline_that_is_no_number_is_refused_and_the_other_waits_still_end() -> None:
    async with asyncio.timeout(10), platforms("p") as [p]:
        asker = await p.add(Agent("asker"))
        loop = asyncio.get_running_loop()
        with asker.conversation(new_id("c")) as conv:
            with pytest.raises(ValueError, match="a deadline must be a number"):
                await asyncio.wait_for(conv.receive(timeout=math.nan), 5.0)
            with pytest.raises(TypeError):
                await asyncio.wait_for(conv.receive(deadline="soon"), 5.0)  # type: ignore[arg-type]
            # the refused ones left nothing that keeps a later wait from its deadline
            for _ in range(2):
                start = loop.time()
                with pytest.raises(ReplyTimeout, match="no reply from anyone"):
                    await asyncio.wait_for(conv.receive(timeout=0.03), 5.0)
                assert loop.time() >= start + 0.03 - SLACK


async def test_a_stopped_agent_leaves_no_timer_for_the_waits_that_ended() -> None:
    async with asyncio.timeout(10), platforms("p") as [p]:
        answerer = await p.add(Agent("answerer"))

        async def answer(message: ACLMessage) -> None:
            await answerer.send(message.reply(P.INFORM, "ok", sender=answerer.aid))

        answerer.add_handler(MessageTemplate(P.QUERY_REF), answer)
        asker = await p.add(Agent("asker"))
        deadlines = asker._deadlines
        assert deadlines is not None
        for _ in range(3):  # answered at once, asked with an hour to spare
            await asker.ask(msg(asker, answerer.aid, P.QUERY_REF), timeout=3600.0)
        # a wait of a conversation the stop does not close (no id, no key) still ends
        unclosed = asker.conversation(None)
        waiting = asyncio.create_task(unclosed.receive(timeout=0.05))
        await asyncio.sleep(0)
        await p.remove(asker)
        assert len(deadlines) == 1  # the one still waiting
        with pytest.raises(ReplyTimeout):
            await asyncio.wait_for(waiting, 5.0)
        # once it ended, the timer that ended it is not armed again for the others
        assert len(deadlines) == 0
        assert deadlines._timer is None
