"""The session table's two calls on the lane's path, each made in one lock section.

`SessionTable.open_noting` opens a binary envelope itself (not through `open`) and
`SessionTable.seal_binary` seals on the session it chose before without asking
`session_for` again while that one still may seal. Each test fails if its shortcut
differs from the full path: an envelope `open` refuses is refused alike (the same error,
the same sender named, nothing of the window moved), and a chosen session that may no
longer seal (past its lifetime, retired past grace, of a key no longer trusted) is not
sealed on.
"""

from __future__ import annotations

import contextlib
import os
import random
from collections.abc import Callable

import msgpack
import pytest
from test_security_bytes import (
    ACL,
    KEYS,
    T0,
    Clock,
    MacPolicy,
    Platform,
    connect,
    edit,
    make_platform,
)

from agents._exceptions import AuthenticationError, Expired, UnknownSession
from agents._security import Handshake, KeyPair, SecurityPolicy, Session, SessionTable

EncPolicy = SecurityPolicy  # encrypted, encryption required: the default


def pair_of(
    policy: SecurityPolicy, sender: SecurityPolicy | None = None
) -> tuple[Platform, Platform]:
    clock = Clock()
    a = make_platform("uav-a", clock, sender or policy)
    b = make_platform("uav-b", clock, policy)
    connect(a, b)
    return a, b


def _noting(p: Platform) -> Callable[[bytes], tuple[str, bytes]]:
    def opened(envelope: bytes) -> tuple[str, bytes]:
        frm, body, forgets = p.table.open_noting(envelope)
        assert forgets == p.table.forgotten(frm)
        return frm, body

    return opened


# Each case: (receiver's policy, sender's policy, the envelope made of a good one)
_CASES: dict[str, tuple[SecurityPolicy, SecurityPolicy | None, Callable[[bytes], bytes]]] = {
    "good": (EncPolicy(), None, lambda env: env),
    "forged time": (EncPolicy(), None, lambda env: edit(env, 4, int(T0 * 1000) + 1)),
    "forged counter": (EncPolicy(), None, lambda env: edit(env, 5, 7)),
    "forged box": (EncPolicy(), None, lambda env: edit(env, 6, b"\x00" * 40)),
    "unknown session": (EncPolicy(), None, lambda env: edit(env, 3, "A" * 22)),
    "misdirected": (EncPolicy(), None, lambda env: edit(env, 2, "uav-c")),
    "untrusted sender": (EncPolicy(), None, lambda env: edit(env, 1, "uav-c")),
    "not msgpack": (EncPolicy(), None, lambda env: env[:-3]),
    "a counter of 0": (EncPolicy(), None, lambda env: edit(env, 5, 0)),
    "too large": (EncPolicy(), None, lambda env: env[:1] + env[1:] + b"x" * 600_000),
    "unencrypted": (EncPolicy(), MacPolicy(), lambda env: env),
    "short mac": (
        EncPolicy(require_encryption=False),
        MacPolicy(),
        lambda env: edit(env, 7, b"short"),
    ),
    "mac only": (EncPolicy(require_encryption=False), MacPolicy(), lambda env: env),
    "wrong mac": (
        EncPolicy(require_encryption=False),
        MacPolicy(),
        lambda env: edit(env, 7, os.urandom(32)),
    ),
}


def _outcome(
    opener: Callable[[Platform], Callable[[bytes], tuple[str, bytes]]], case: str
) -> object:
    policy, sender, change = _CASES[case]
    a, b = pair_of(policy, sender)
    first = a.table.seal_binary("uav-b", ACL)
    envelope = change(a.table.seal_binary("uav-b", ACL))
    open_ = opener(b)
    sid = b.table.sessions()[0].sid

    def attempt(envelope: bytes) -> object:
        try:
            return open_(envelope)
        except AuthenticationError as exc:
            return type(exc), exc.code, exc.platform, str(exc).replace(sid, "SID")

    got = attempt(envelope)
    # what the window says after: the first envelope opens, or not, as it would have
    after = attempt(first)
    return got, after, b.table.heard_since("uav-a") is not None, len(b.table._rx_latest)


@pytest.mark.parametrize("case", sorted(_CASES))
def test_open_noting_opens_and_refuses_as_open(case: str) -> None:
    assert _outcome(_noting, case) == _outcome(lambda p: p.table.open, case)


def test_open_noting_reads_the_forgets_of_the_moment() -> None:
    a, b = pair_of(EncPolicy())
    assert b.table.open_noting(a.table.seal_binary("uav-b", ACL)) == ("uav-a", ACL, 0)
    b.table.forget("uav-a")
    a.table.forget("uav-b")
    connect(a, b)
    assert b.table.open_noting(a.table.seal_binary("uav-b", ACL)) == ("uav-a", ACL, 1)


def _chosen(policy: SecurityPolicy | None = None) -> tuple[Platform, Platform, Clock]:
    """``a`` has sealed once: its table's choice for ``uav-b`` is kept."""
    clock = Clock()
    policy = policy or EncPolicy()
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    b.table.open(a.table.seal_binary("uav-b", ACL))
    assert a.table._tx.get("uav-b") is not None
    return a, b, clock


def test_a_chosen_session_past_its_lifetime_seals_nothing() -> None:
    a, _, clock = _chosen(EncPolicy(renew_after_seconds=100, grace=10))
    clock.t += 110.001
    with pytest.raises(UnknownSession):
        a.table.seal_binary("uav-b", ACL)


def test_a_chosen_session_past_its_lifetime_gives_way_to_a_newer_one() -> None:
    a, b, clock = _chosen(EncPolicy(renew_after_seconds=100, grace=10))
    clock.t += 50
    newer, _ = connect(a, b)  # made by a: confirmed; the old one stays the choice until...
    a.table._tx["uav-b"] = a.table.sessions("uav-b")[0]  # ...as if chosen before it came
    clock.t += 60.001  # the old one is past its lifetime, the newer is not
    b.table.open(a.table.seal_binary("uav-b", ACL))
    assert a.table._tx["uav-b"] is newer


def test_a_chosen_session_retired_past_grace_seals_nothing() -> None:
    a, _, clock = _chosen(EncPolicy(grace=10))
    session = a.table._tx["uav-b"]
    session._retire_at = clock.t + 10  # retired elsewhere, the choice not yet dropped
    clock.t += 10
    a.table.seal_binary("uav-b", ACL)  # within grace: still sealed on
    clock.t += 0.001
    with pytest.raises(UnknownSession):
        a.table.seal_binary("uav-b", ACL)


def test_a_chosen_session_of_a_key_no_longer_trusted_seals_nothing() -> None:
    a, _, _ = _chosen()
    assert a.table.trust.add("uav-b", KeyPair.generate("uav-b").public_key, replace=True)
    with pytest.raises(UnknownSession):
        a.table.seal_binary("uav-b", ACL)


def _full_path_choice(table: SessionTable, peer: str) -> Session | None:
    """What `session_for` (the full path) would choose now, the table left as it was."""
    with table._lock:
        kept = dict(table._tx)
        chosen = SessionTable.session_for(table, peer)
        table._tx.clear()
        table._tx.update(kept)
        return chosen


def _random_run(seed: int) -> tuple[int, int]:
    """One random sequence, every seal checked; how many seals found a choice kept that
    still holds (the shortcut) and one that no longer does (the full path after it)."""
    rnd = random.Random(seed)
    clock = Clock()
    policy = EncPolicy(renew_after_seconds=100, grace=10, max_sessions_per_peer=rnd.choice([2, 4]))
    platforms = {name: make_platform(name, clock, policy) for name in ("uav-a", "uav-b")}
    strangers = {name: KeyPair.generate(name).public_key for name in platforms}
    sent: list[tuple[str, bytes]] = []
    kept_choice = stale_choice = 0
    for _ in range(250):
        me, peer = rnd.sample(sorted(platforms), 2)
        p, table = platforms[me], platforms[me].table
        op = rnd.random()
        if op < 0.15:
            clock.t += rnd.choice([0.0, 0.5, 5, 10.0005, 30, 60, 100.001])
        elif op < 0.25:
            try:
                connect(p, platforms[peer])
            except AuthenticationError:
                pass  # a key rotated away: no handshake
            clock.t += 0.002  # no two sessions agreed at the same time
        elif op < 0.6:
            expected = _full_path_choice(table, peer)
            before = table._tx.get(peer)
            kept_choice += before is not None and before is expected
            stale_choice += before is not None and before is not expected
            if expected is None:
                with pytest.raises(UnknownSession):
                    table.seal_binary(peer, ACL)
                continue
            envelope = table.seal_binary(peer, ACL)
            assert msgpack.unpackb(envelope)[3] == expected.sid
            sent.append((peer, envelope))
        elif op < 0.8 and sent:
            i = rnd.randrange(len(sent))
            to, envelope = sent[i] if rnd.random() < 0.2 else sent.pop(i)  # some twice
            with contextlib.suppress(AuthenticationError):
                platforms[to].table.open_noting(envelope)
        elif op < 0.84:
            table.doubt(peer)
        elif op < 0.88:
            table.retire(peer, None if rnd.random() < 0.5 else clock.t - rnd.choice([0, 50]))
        elif op < 0.9:
            table.forget(peer)
        elif op < 0.95:
            key = rnd.choice([strangers[peer], KEYS[peer].public_key, bytes(KEYS[peer].public_key)])
            table.trust.add(peer, key, replace=True)
        elif op < 0.97:
            table.trust.remove(peer)
        else:
            table.prune()
        if peer not in table.trust and rnd.random() < 0.5:
            table.trust.add(peer, bytes(KEYS[peer].public_key))  # trusted again, by value
    return kept_choice, stale_choice


def test_seal_binary_seals_on_the_session_the_full_path_chooses() -> None:
    # random sequences of renewals, time, opens (replays too), doubt, retire, forget,
    # prune and trust changes (rotated, rotated back by value, removed): every seal is
    # on the session `session_for` would choose, or refused where it chooses none
    kept, stale = map(sum, zip(*(_random_run(seed) for seed in range(16)), strict=True))
    assert kept > 50 and stale > 5  # both ways through `seal_binary` were taken


def test_a_chosen_session_of_another_clock_seals_at_its_own_reading() -> None:
    """A session whose clock is not its table's (its handshake's own) is sealed at its own
    clock's reading, also when chosen before: its time stamp, and its lifetime told by it."""
    clock, ahead = Clock(), Clock()
    policy = EncPolicy(renew_after_seconds=100, grace=10)
    trust = make_platform("uav-a", clock, policy).table.trust
    a = Platform(
        Handshake(KEYS["uav-a"], trust, policy=policy, clock=ahead),
        SessionTable("uav-a", trust, policy=policy, clock=clock),
    )
    connect(a, make_platform("uav-b", ahead, policy))
    a.table.seal_binary("uav-b", ACL)
    assert a.table._tx.get("uav-b") is not None  # chosen: the next seal takes the shortcut
    ahead.t += 5
    assert msgpack.unpackb(a.table.seal_binary("uav-b", ACL))[4] == int(ahead.t * 1000)
    ahead.t += 105.001  # past its lifetime by its clock, not by the table's
    with pytest.raises(Expired):
        a.table.seal_binary("uav-b", ACL)
