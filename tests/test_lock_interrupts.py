"""The lock sections taken on the event loop's thread (a lone reply's: `InterfaceAgent._lane_book`,
`_lane_take_reply`; every message's seal: `SessionTable.seal_binary`, `needs_renewal`): an
interrupt there never leaves a lock held.

The loop's thread is the main one, where CPython runs a signal's Python handler (Ctrl-C's
KeyboardInterrupt, the demo's SIGTERM turned into one) at the check that follows a call's
return: the instruction right after ``lock.acquire()``. A lock held past an interrupt is held
for ever: zenoh's thread blocks on the lane's lock at the next envelope, and the stop's own
`_lane_book` on the loop's. The probe raises the interrupt at the first instruction run once
a lock is taken, as that pending handler would; real zenoh sessions on loopback (the pair of
`tests/test_answer_on_thread.py`, the asker ``operator`` with the lane).
"""

from __future__ import annotations

import sys
import threading
from types import FrameType
from typing import Any

import pytest

import agents._interface as interface
import agents._security as security
from tests.test_answer_on_thread import pair
from tests.test_reply_on_thread import _asked, _reply, _warm
from tests.test_security import Clock, connect, make_platform

_HERE = {sys.modules[c.__module__].__file__ for c in interface.InterfaceAgent.__mro__[:-1]}


@pytest.mark.parametrize(
    "nth", [1, 2, 3], ids=["lane-lock-booking", "sender-lock-taking", "lane-lock-release"]
)
async def test_an_interrupt_the_moment_a_lock_is_taken_on_the_loop_leaves_it_free(
    nth: int,
) -> None:
    """The nth lock taken while the loop takes a lone reply (the booking's lane lock, the
    sender's buckets, the count's release): interrupted right there, it is released."""
    async with pair(lane=False, asker_lane=True) as p:
        ia = p.ia_op
        await _warm(p)
        request, asked = await _asked(p, f"interrupt-{nth}")
        assert ia._lane_take(_reply(p, request)) is None  # handed over
        state = ia._senders["uav-a"]
        locks = (ia._lane_lock, state.lock)
        assert not any(lock.locked() for lock in locks)
        taken = [0]  # the locks seen taken so far
        held = [False]

        def local(frame: FrameType, event: str, arg: Any) -> Any:
            if event == "opcode":
                now = any(lock.locked() for lock in locks)
                if now and not held[0]:
                    taken[0] += 1
                    if taken[0] == nth:
                        raise KeyboardInterrupt  # as a signal's handler, pending meanwhile
                held[0] = now
            return local

        def tracer(frame: FrameType, event: str, arg: Any) -> Any:
            if frame.f_code.co_filename not in _HERE:
                return None
            frame.f_trace_opcodes = True
            return local

        try:
            previous = sys.gettrace()  # a coverage tool's, say: put back after
            sys.settrace(tracer)
            try:
                with pytest.raises(KeyboardInterrupt):
                    ia._lane_book()
            finally:
                sys.settrace(previous)
            assert taken[0] == nth
            left = [lock.locked() for lock in locks]
            assert left == [False, False], f"held after the interrupt (lane, sender): {left}"
        finally:
            for lock in locks:  # the pair's stop must not hang on what the probe found
                if lock.locked():
                    lock.release()
            asked.cancel()


@pytest.mark.parametrize("method", ["seal_binary", "needs_renewal"])
def test_an_interrupt_the_moment_the_session_table_s_lock_is_taken_leaves_it_free(
    method: str,
) -> None:
    """Every message sealed on the loop takes the table's lock; interrupted the moment it has
    it, the lock is free again for zenoh's thread (whose lane seals its answers)."""
    clock = Clock()
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    table = a.table
    lock = table._lock

    def call() -> object:
        if method == "seal_binary":
            return table.seal_binary("uav-b", b'{"x":1}')
        return table.needs_renewal("uav-b")

    call()  # the usual path, as every message after the first takes it
    fired = [False]

    def local(frame: FrameType, event: str, arg: Any) -> Any:
        if event == "opcode" and not fired[0] and lock._is_owned():
            fired[0] = True
            raise KeyboardInterrupt  # as a signal's handler, pending meanwhile
        return local

    def tracer(frame: FrameType, event: str, arg: Any) -> Any:
        if frame.f_code.co_filename != security.__file__:
            return None
        frame.f_trace_opcodes = True
        return local

    previous = sys.gettrace()
    sys.settrace(tracer)
    try:
        with pytest.raises(KeyboardInterrupt):
            call()
    finally:
        sys.settrace(previous)
    assert fired[0]
    got: list[bool] = []
    other = threading.Thread(target=lambda: got.append(lock.acquire(timeout=5)))
    other.start()
    other.join(10)
    assert got == [True], "the table's lock was left held by the interrupted thread"
