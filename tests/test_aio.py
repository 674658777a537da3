"""The asyncio helpers: Mailbox (deadline, cancellation, order, overflow), Ticker (drift),
Pending (asleep when idle, at once after a quiet spell, at most once per period),
sleep_until_woken, and the Inbox's own record of its loop's thread."""

from __future__ import annotations

import asyncio
import threading

import pytest

from agents import Mailbox, Pending, Ticker, TransportClosed, call_in_loop
from agents._aio import together
from agents.transports import Inbox, Subscription
from dyknow_core import Clock, ManualClock, RealClock
from dyknow_core._aio import Ticker as CoreTicker
from dyknow_core._aio import sleep_until_woken

# -- Mailbox ------------------------------------------------------------------------------------


async def test_items_come_out_in_order() -> None:
    box: Mailbox[int] = Mailbox(10)
    for n in range(5):
        assert box.put(n)
    assert [await box.get() for _ in range(5)] == [0, 1, 2, 3, 4]
    assert len(box) == 0


def test_get_all_nowait_takes_what_is_queued_in_order() -> None:
    box: Mailbox[int] = Mailbox(4)
    assert box.get_all_nowait() == []
    for i in range(3):
        box.put(i)
    assert box.get_all_nowait() == [0, 1, 2]
    assert len(box) == 0
    box.put(3)
    assert box.get_nowait() == 3


async def test_a_waiting_consumer_gets_the_next_item() -> None:
    box: Mailbox[str] = Mailbox(10)
    getting = asyncio.create_task(box.get())
    await asyncio.sleep(0)
    assert not getting.done()
    box.put("a")
    assert await getting == "a"


async def test_get_raises_timeout_at_the_deadline() -> None:
    box: Mailbox[int] = Mailbox(10)
    loop = asyncio.get_running_loop()
    start = loop.time()
    with pytest.raises(TimeoutError):
        await box.get(deadline=start + 0.05)
    assert loop.time() - start >= 0.04
    assert box._waiter is None  # nothing left behind for a later put to wake


async def test_a_deadline_already_past_still_returns_what_is_queued() -> None:
    box: Mailbox[int] = Mailbox(10)
    box.put(7)
    assert await box.get(deadline=asyncio.get_running_loop().time() - 1.0) == 7
    with pytest.raises(TimeoutError):
        await box.get(deadline=asyncio.get_running_loop().time() - 1.0)


async def test_an_item_before_the_deadline_wins() -> None:
    box: Mailbox[int] = Mailbox(10)
    loop = asyncio.get_running_loop()
    loop.call_later(0.01, box.put, 1)
    assert await box.get(deadline=loop.time() + 5.0) == 1


async def test_a_cancelled_get_leaves_the_items_for_the_next() -> None:
    box: Mailbox[int] = Mailbox(10)
    getting = asyncio.create_task(box.get(deadline=asyncio.get_running_loop().time() + 5.0))
    await asyncio.sleep(0)
    getting.cancel()
    with pytest.raises(asyncio.CancelledError):
        await getting
    box.put(3)
    assert await box.get() == 3


async def test_a_full_box_refuses_or_drops_the_oldest() -> None:
    refusing: Mailbox[int] = Mailbox(2)
    assert refusing.put(1) and refusing.put(2)
    assert not refusing.put(3)
    assert refusing.dropped == 1
    assert [refusing.get_nowait(), refusing.get_nowait()] == [1, 2]

    dropping: Mailbox[int] = Mailbox(2, drop_oldest=True)
    dropping.put(1)
    dropping.put(2)
    assert not dropping.put(3)
    assert dropping.dropped == 1
    assert [dropping.get_nowait(), dropping.get_nowait()] == [2, 3]
    with pytest.raises(asyncio.QueueEmpty):
        dropping.get_nowait()


async def test_forced_and_front_items_pass_a_full_box() -> None:
    box: Mailbox[int] = Mailbox(1)
    box.put(1)
    assert box.put(2, force=True)
    box.put_front(0)
    assert [box.get_nowait() for _ in range(3)] == [0, 1, 2]
    assert box.dropped == 0


class _CountingBox(Mailbox[int]):
    """A Mailbox that counts its wakes."""

    def __init__(self, maxlen: int, *, drop_oldest: bool = False) -> None:
        super().__init__(maxlen, drop_oldest=drop_oldest)
        self.wakes = 0

    def _wake(self) -> None:
        self.wakes += 1
        super()._wake()


@pytest.mark.parametrize("drop_oldest", [False, True])
def test_put_many_keeps_the_accounting_of_a_put_per_item(drop_oldest: bool) -> None:
    for maxlen in range(1, 5):
        for queued in range(6):  # beyond maxlen: forced items
            for n in range(7):
                one: Mailbox[int] = Mailbox(maxlen, drop_oldest=drop_oldest)
                many: Mailbox[int] = Mailbox(maxlen, drop_oldest=drop_oldest)
                for box in (one, many):
                    for q in range(queued):
                        box.put(-q, force=True)
                batch = list(range(n))
                fitted = sum(one.put(x) for x in batch)
                case = (maxlen, queued, n)
                assert many.put_many(batch) == fitted, case
                assert many.dropped == one.dropped, case
                assert list(many._items) == list(one._items), case


@pytest.mark.parametrize(
    ("drop_oldest", "queued", "n", "wakes"),
    [
        (False, 0, 3, 1),  # one wake for the batch
        (False, 2, 3, 1),  # some refused: still woken for the rest
        (False, 4, 3, 0),  # all refused: nothing to wake for
        (False, 0, 0, 0),  # nothing put
        (True, 4, 3, 1),  # each pushed the oldest out: woken once
    ],
)
def test_put_many_wakes_the_consumer_once_if_anything_went_in(
    drop_oldest: bool, queued: int, n: int, wakes: int
) -> None:
    box = _CountingBox(4, drop_oldest=drop_oldest)
    for q in range(queued):
        box.put(q)
    box.wakes = 0
    box.put_many(range(10, 10 + n))
    assert box.wakes == wakes


async def test_put_many_wakes_a_waiting_consumer_with_the_whole_batch() -> None:
    box: Mailbox[int] = Mailbox(10)
    getting = asyncio.create_task(box.get())
    await asyncio.sleep(0)
    assert box.put_many([1, 2, 3]) == 3
    assert await getting == 1
    assert [box.get_nowait(), box.get_nowait()] == [2, 3]


def test_a_mailbox_needs_room() -> None:
    with pytest.raises(ValueError, match="maxlen"):
        Mailbox(0)


# -- Ticker -------------------------------------------------------------------------------------


@pytest.mark.parametrize("ticker_class", [Ticker, CoreTicker])
async def test_ticks_stay_on_the_grid_whatever_the_body_takes(ticker_class: type[Ticker]) -> None:
    loop = asyncio.get_running_loop()
    period = 0.05
    start = loop.time()
    ticker = ticker_class(period, first=start + period)
    ticks = []
    for _ in range(5):
        due = await ticker.tick()
        assert loop.time() >= due  # never early
        ticks.append(round((due - start) / period, 6))
        await asyncio.sleep(period / 2)  # a body taking half a period does not add up
    # every tick on the grid k * period (no drift); under load one may be skipped, not shifted
    assert ticks == sorted(set(ticks))
    assert all(k == int(k) for k in ticks)
    assert ticks[-1] - ticks[0] == 4 + ticker.skipped


@pytest.mark.parametrize("ticker_class", [Ticker, CoreTicker])
async def test_an_overrun_skips_the_missed_ticks(ticker_class: type[Ticker]) -> None:
    loop = asyncio.get_running_loop()
    period = 0.02
    ticker = ticker_class(period)
    first = await ticker.tick()
    await asyncio.sleep(period * 3.5)  # the body overruns: three more ticks are past
    second = await ticker.tick()
    now = loop.time()
    # the latest one past runs at once, on the grid; the ones before it are skipped
    assert ticker.skipped >= 2
    assert second == pytest.approx(first + (ticker.skipped + 1) * period)
    assert second <= now < second + period


# -- Pending ------------------------------------------------------------------------------------


async def test_pending_sleeps_until_a_count_comes_from_another_thread() -> None:
    loop = asyncio.get_running_loop()
    pending = Pending(10.0)
    taking = asyncio.create_task(pending.take())
    await asyncio.sleep(0.05)
    assert not taking.done()  # nothing pending: asleep, however long the period
    added = loop.time()
    threading.Thread(target=pending.add, args=(3,)).start()
    # the first count after a quiet spell is taken at once, not a period later
    assert await asyncio.wait_for(taking, 1.0) == 3
    assert loop.time() - added < 1.0


async def test_pending_sums_up_what_comes_within_a_period() -> None:
    loop = asyncio.get_running_loop()
    period = 0.1
    pending = Pending(period)
    pending.add()
    assert await pending.take() == 1
    taken = loop.time()
    pending.add()
    pending.add(2)
    assert await pending.take() == 3  # summed up, and not before a period has passed
    assert loop.time() - taken >= period * 0.99
    assert pending.period == period
    with pytest.raises(ValueError, match="period"):
        Pending(0)


async def test_the_period_may_change_between_ticks() -> None:
    loop = asyncio.get_running_loop()
    ticker = Ticker(0.01)
    first = await ticker.tick()
    ticker.period = 0.03
    skipped = ticker.skipped
    second = await ticker.tick()
    # already due at the old period; a task run a whole new period late (a busy machine)
    # skips ticks of the new one, on its grid
    assert second == pytest.approx(first + 0.01 + 0.03 * (ticker.skipped - skipped))
    skipped = ticker.skipped
    third = await ticker.tick()
    assert third == pytest.approx(second + 0.03 * (1 + ticker.skipped - skipped))
    assert loop.time() >= third


async def test_a_ticker_is_an_async_iterator() -> None:
    seen = 0
    async for _ in Ticker(0.001):
        seen += 1
        if seen == 3:
            break
    assert seen == 3


@pytest.mark.parametrize("period", [0.0, -1.0, float("inf"), float("nan")])
def test_a_period_must_be_positive(period: float) -> None:
    with pytest.raises(ValueError, match="period"):
        Ticker(period)
    with pytest.raises(ValueError, match="period"):
        CoreTicker(period)


async def test_a_cancelled_tick_leaves_the_loop_clean() -> None:
    ticking = asyncio.create_task(Ticker(10.0).tick())
    await asyncio.sleep(0)
    ticking.cancel()
    with pytest.raises(asyncio.CancelledError):
        await ticking


# -- sleep_until_woken ---------------------------------------------------------------------------


async def test_sleep_until_woken_ends_at_the_deadline_or_when_woken() -> None:
    clock = ManualClock(0)
    wake = asyncio.Event()
    sleeping = asyncio.create_task(sleep_until_woken(clock, 100, wake))
    await asyncio.sleep(0)
    clock.advance(50)
    await asyncio.sleep(0)
    assert not sleeping.done()
    clock.advance(50)
    await asyncio.wait_for(sleeping, 1.0)

    sleeping = asyncio.create_task(sleep_until_woken(clock, None, wake))  # no deadline
    await asyncio.sleep(0)
    assert not sleeping.done()
    wake.set()
    await asyncio.wait_for(sleeping, 1.0)
    assert asyncio.all_tasks() == {asyncio.current_task()}  # the waits it started ended


async def test_sleep_until_woken_cancelled_leaves_no_task_of_its_own() -> None:
    sleeping = asyncio.create_task(
        sleep_until_woken(ManualClock(0), 100, asyncio.Event()), name="timer"
    )
    await asyncio.sleep(0)
    waits = {t.get_name() for t in asyncio.all_tasks()} - {"timer"}
    assert {"timer.wake", "timer.deadline"} <= waits  # named after the task that sleeps
    sleeping.cancel()
    await asyncio.wait([sleeping])
    assert asyncio.all_tasks() == {asyncio.current_task()}


@pytest.mark.parametrize("clock", [RealClock(), ManualClock(0)], ids=["real", "manual"])
async def test_a_timer_without_a_deadline_resumes_on_the_turn_it_is_woken(clock: Clock) -> None:
    """Woken, it resumes with the event's own waiters, and started nothing to wait for."""
    wake = asyncio.Event()
    sleeping = asyncio.create_task(sleep_until_woken(clock, None, wake))
    await asyncio.sleep(0)
    assert asyncio.all_tasks() == {asyncio.current_task(), sleeping}
    wake.set()
    await asyncio.sleep(0)  # one turn: the sleeper's, queued before this task's
    assert sleeping.done()
    await sleeping


async def test_a_wall_clock_timer_resumes_on_the_turn_it_is_woken() -> None:
    """On the wall clock, a woken timer resumes at once; the wake stays set for the next wait."""
    clock, wake = RealClock(), asyncio.Event()
    sleeping = asyncio.create_task(sleep_until_woken(clock, clock.now() + 10**12, wake))
    await asyncio.sleep(0)
    assert asyncio.all_tasks() == {asyncio.current_task(), sleeping}  # no wait of its own
    wake.set()
    await asyncio.sleep(0)
    assert sleeping.done()
    await sleeping
    # not consumed: a timer that did not clear it before its next wait does not sleep
    await asyncio.wait_for(sleep_until_woken(clock, clock.now() + 10**12, wake), 1.0)
    # the deadline, as before; one past already still yields to the others once
    wake.clear()
    t0 = clock.now()
    await asyncio.wait_for(sleep_until_woken(clock, t0 + 20_000_000, wake), 1.0)
    assert clock.now() >= t0 + 20_000_000
    others: list[int] = []
    asyncio.get_running_loop().call_soon(others.append, 1)
    await sleep_until_woken(clock, t0, wake)
    assert others == [1]
    # cancelled, it is cancelled (not taken for its deadline), and leaves nothing behind
    sleeping = asyncio.create_task(sleep_until_woken(clock, clock.now() + 10**12, wake))
    await asyncio.sleep(0)
    sleeping.cancel()
    with pytest.raises(asyncio.CancelledError):
        await sleeping
    assert asyncio.all_tasks() == {asyncio.current_task()}


# -- Inbox: the loop's thread is its own, not asyncio's private attribute ------------------------


async def test_an_inbox_wakes_its_consumer_from_the_loop_thread_and_from_others() -> None:
    loop = asyncio.get_running_loop()
    inbox: Inbox[int] = Inbox(loop)
    getting = asyncio.create_task(inbox.get())
    await asyncio.sleep(0)
    assert inbox._loop_thread == threading.get_ident()  # recorded by the waiting consumer
    inbox.put(1)  # on the loop's thread: woken directly
    assert await asyncio.wait_for(getting, 1.0) == 1

    getting = asyncio.create_task(inbox.get())
    await asyncio.sleep(0)
    producer = threading.Thread(target=inbox.put, args=(2,))
    producer.start()
    assert await asyncio.wait_for(getting, 1.0) == 2
    producer.join()


async def test_an_inbox_wait_cancelled_or_woken_leaves_the_next_one_wakeable() -> None:
    """The wake-up clears the waiter, a cancelled wait its own: either way the next wait wakes."""
    loop = asyncio.get_running_loop()
    inbox: Inbox[int] = Inbox(loop)
    getting = asyncio.create_task(inbox.get())
    await asyncio.sleep(0)
    getting.cancel()
    await asyncio.wait([getting])
    assert inbox._waiter is None
    for i in range(3):  # woken, then waiting again at once
        getting = asyncio.create_task(inbox.get())
        await asyncio.sleep(0)
        threading.Thread(target=inbox.put, args=(i,)).start()
        assert await asyncio.wait_for(getting, 1.0) == i
        assert inbox._waiter is None
    iterating = asyncio.create_task(_drained(Subscription(inbox, lambda: None)))
    await asyncio.sleep(0)
    inbox.put(7)
    inbox.close()
    assert await asyncio.wait_for(iterating, 1.0) == [7]  # ends on close, as ever
    with pytest.raises(TransportClosed):
        await inbox.get()


async def _drained(sub: Subscription[int]) -> list[int]:
    return [item async for item in sub]


async def test_call_in_loop_calls_at_once_in_its_loop_and_later_from_another_thread() -> None:
    """In the loop's own thread the call is made before `call_in_loop` returns; from another
    thread it is made in the loop's thread, not the caller's."""
    loop = asyncio.get_running_loop()
    calls: list[tuple[str, int]] = []
    call_in_loop(loop, lambda what: calls.append((what, threading.get_ident())), "here")
    assert calls == [("here", threading.get_ident())]
    done = asyncio.Event()

    def there(what: str) -> None:
        calls.append((what, threading.get_ident()))
        done.set()

    worker = threading.Thread(target=call_in_loop, args=(loop, there, "from a thread"))
    worker.start()
    worker.join(timeout=5)
    async with asyncio.timeout(5):
        await done.wait()
    assert calls[1] == ("from a thread", threading.get_ident())  # the loop's thread
    call_in_loop(None, calls.append, ("no loop", 0))
    assert calls[2] == ("no loop", 0)


# -- together -----------------------------------------------------------------------------------


async def test_together_raises_a_step_s_failure_as_the_step_raised_it() -> None:
    async def fails() -> None:
        await asyncio.sleep(0)
        raise ValueError("step failed")

    other = asyncio.Event()

    async def waits() -> None:
        await other.wait()

    with pytest.raises(ValueError, match="step failed"):
        async with asyncio.timeout(10.0):
            await together(fails(), waits())


async def test_together_in_a_task_being_cancelled_raises_the_cancellation_not_a_step_s_error() -> (
    None
):
    # the TaskGroup under it raises its steps' errors over its own task's cancellation: a
    # caller cancelled while a step failed took the step's error for the outcome, and a
    # loop that catches it went on, its cancellation lost
    go = asyncio.Event()
    started = asyncio.Event()
    cleaned: list[str] = []

    async def fails_at_go() -> None:
        started.set()
        await go.wait()
        raise ValueError("step failed")

    async def waits() -> None:
        try:
            await asyncio.Event().wait()
        finally:
            cleaned.append("waits")

    caught: list[BaseException] = []

    async def caller() -> None:
        try:
            await together(fails_at_go(), waits())
        except ValueError as exc:  # what a caller catches from a failing step
            caught.append(exc)

    task = asyncio.create_task(caller())
    async with asyncio.timeout(10.0):
        await started.wait()
    go.set()  # the step fails in the same turn as its caller's cancellation
    task.cancel()
    async with asyncio.timeout(10.0):
        await asyncio.wait([task])
    assert caught == []
    assert task.cancelled()
    assert cleaned == ["waits"]


async def test_an_inbox_take_hands_out_up_to_its_limit_in_order_converted() -> None:
    """`take` gives what is queued now, oldest first, at most ``limit`` (converted as `get`
    would), leaves the rest for the next get, and never waits."""
    inbox: Inbox[str] = Inbox(asyncio.get_running_loop(), convert=lambda i: f"#{i}")
    assert inbox.take(5) == []  # nothing queued: nothing, at once
    for i in range(5):
        inbox.put(i)  # type: ignore[arg-type]  # the raw item; `convert` makes the str
    assert inbox.take(3) == ["#0", "#1", "#2"]
    assert inbox.take(0) == [] and len(inbox) == 2
    assert await inbox.get() == "#3"
    assert inbox.take(10) == ["#4"]
    assert inbox.received == 5 and inbox.dropped == 0
