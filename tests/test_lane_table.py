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

import os
from collections.abc import Callable

import pytest
from test_security_bytes import ACL, T0, Clock, MacPolicy, Platform, connect, edit, make_platform

from agents._exceptions import AuthenticationError, UnknownSession
from agents._security import KeyPair, SecurityPolicy

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
