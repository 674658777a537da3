"""A session table's answer "no renewal due" is kept per peer, and dropped by each change.

`SessionTable.needs_renewal` is asked after every message sent; once it said False for a
peer, it says False again from what it kept while nothing of that peer changed, the
clock is before the renewal time and the kept session's message budget holds. Each test
here asks first (so the answer is kept), then makes one change that makes a renewal due,
and asks again: each fails if that change does not drop what was kept.
"""

from __future__ import annotations

import pytest

from agents._security import Handshake, KeyPair
from tests.test_security import ACL, KEYS, Clock, MacPolicy, Platform, connect, make_platform


@pytest.fixture
def clock() -> Clock:
    return Clock()


def kept(p: Platform, peer: str) -> bool:
    """Whether ``p``'s table keeps an answer for ``peer`` (asked once first: not due)."""
    assert not p.table.needs_renewal(peer)
    return peer in p.table._renew_due


def test_the_answer_is_kept_until_the_renewal_time(clock: Clock) -> None:
    policy = MacPolicy(renew_after_seconds=100, grace=10)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    assert kept(a, "uav-b")
    clock.advance(99.9)
    assert not a.table.needs_renewal("uav-b")
    clock.advance(0.1)
    assert a.table.needs_renewal("uav-b")


def test_the_responders_answer_is_kept_until_its_later_renewal_time(clock: Clock) -> None:
    # the responder leaves the first move to the initiator: its renewal is grace / 2 later
    policy = MacPolicy(renew_after_seconds=100, grace=10)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    b.table.open(a.table.seal("uav-b", ACL))  # confirmed at b: b seals on it
    assert kept(b, "uav-a")
    clock.advance(104.9)
    assert not b.table.needs_renewal("uav-a")
    clock.advance(0.1)
    assert b.table.needs_renewal("uav-a")


def test_the_message_budget_is_checked_every_time(clock: Clock) -> None:
    policy = MacPolicy(renew_after_messages=5)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    assert kept(a, "uav-b")
    for _ in range(4):
        a.table.seal("uav-b", ACL)
    assert not a.table.needs_renewal("uav-b")
    a.table.seal("uav-b", ACL)
    assert a.table.needs_renewal("uav-b")


def test_forget_drops_the_answer(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    assert kept(a, "uav-b")
    assert a.table.forget("uav-b") == 1
    assert a.table.needs_renewal("uav-b")


def test_doubt_drops_the_answer(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    assert kept(a, "uav-b")
    assert a.table.doubt("uav-b") == 1
    assert a.table.needs_renewal("uav-b")


def test_retire_drops_the_answer(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    assert kept(a, "uav-b")
    assert a.table.retire("uav-b") == 1
    assert a.table.needs_renewal("uav-b")


def test_a_new_session_drops_the_answer(clock: Clock) -> None:
    # renewed: the new session is sealed on, and its own message budget counts
    policy = MacPolicy(renew_after_messages=5)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    assert kept(a, "uav-b")
    clock.advance(0.01)
    sa2, _ = connect(a, b)
    for _ in range(5):
        a.table.seal("uav-b", ACL)
    assert a.table.session_for("uav-b") is sa2 and sa2.sent == 5
    assert a.table.needs_renewal("uav-b")


def test_a_session_dropped_to_make_room_drops_the_answer(clock: Clock) -> None:
    # at the responder, one session a peer: a renewal's new session, not confirmed yet,
    # pushes out the confirmed one, and none is left to seal on
    policy = MacPolicy(max_sessions_per_peer=1)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    b.table.open(a.table.seal("uav-b", ACL))
    assert kept(b, "uav-a")
    clock.advance(0.01)
    connect(a, b)
    assert b.table.session_for("uav-a") is None
    assert b.table.needs_renewal("uav-a")


def test_the_peer_moving_to_a_new_session_drops_the_answer(clock: Clock) -> None:
    # at the responder: the peer's renewal is confirmed when it sends on it, and from
    # then on the new session is sealed on, with its own message budget
    policy = MacPolicy(renew_after_messages=5)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    b.table.open(a.table.seal("uav-b", ACL))
    clock.advance(0.01)
    _, sb2 = connect(a, b)
    assert kept(b, "uav-a")  # asked after the new session came: the old one still counts
    b.table.open(a.table.seal("uav-b", ACL))  # a sends on the new one
    for _ in range(5):
        b.table.seal("uav-a", ACL)
    assert b.table.session_for("uav-a") is sb2 and sb2.sent == 5
    assert b.table.needs_renewal("uav-a")


@pytest.mark.parametrize("change", ["rotated", "removed"])
def test_a_change_of_trust_drops_the_answer(clock: Clock, change: str) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    assert kept(a, "uav-b")
    if change == "rotated":
        assert a.trust.add("uav-b", KEYS["uav-c"].public_key, replace=True)
    else:
        a.trust.remove("uav-b")
    assert a.table.needs_renewal("uav-b")


def test_a_retired_session_is_asked_in_full_until_its_retirement(clock: Clock) -> None:
    # retired within its grace (`_on_rx_switch` sets that on a session it moves away from)
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    sa, _ = connect(a, b)
    sa._retire_at = clock() + 10
    assert not a.table.needs_renewal("uav-b")
    clock.advance(10.5)
    assert a.table.needs_renewal("uav-b")


def test_a_session_on_another_clock_than_its_tables_is_asked_by_its_own(clock: Clock) -> None:
    # what is kept is told by the table's clock: a session reading another one is asked
    # in full every time, as `Session.needs_renewal` reads its own clock
    policy = MacPolicy(renew_after_seconds=100, grace=10)
    other = Clock(clock())
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    a.hs = Handshake(KEYS["uav-a"], a.trust, policy=policy, clock=other)
    connect(a, b)
    assert not a.table.needs_renewal("uav-b")
    other.advance(100)
    assert a.table.needs_renewal("uav-b")


def test_a_session_of_a_key_no_longer_trusted_asks_for_renewal() -> None:
    """`needs_renewal` is True when there is no session to seal with (its docstring),
    as `session_for` says after a re-key: the renewal asked after each message sent must
    not take the session of the old key for a fresh one."""
    clock = Clock()
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    b.table.open(a.table.seal("uav-b", ACL))
    assert not a.table.needs_renewal("uav-b")  # fresh, of the key trusted
    assert a.trust.add("uav-b", KeyPair.generate("uav-x").public_key, replace=True)
    assert a.table.session_for("uav-b") is None
    assert a.table.needs_renewal("uav-b")
    # the agreed key back, in another key object (as another store holds it): by value
    assert a.trust.add("uav-b", KEYS["uav-b"].public_key, replace=True)
    assert a.table.session_for("uav-b") is not None
    assert not a.table.needs_renewal("uav-b")
    a.trust.remove("uav-b")
    assert a.table.needs_renewal("uav-b")
