"""Platform keys, trust file, authenticated key exchange and sealed envelopes (agents._security)."""

from __future__ import annotations

import base64
import binascii
import functools
import json
import os
import stat
import string
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import orjson
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agents._exceptions import (
    AuthenticationError,
    Expired,
    Forged,
    KeyFileError,
    Malformed,
    MessageError,
    Misdirected,
    Replayed,
    SecurityError,
    Unencrypted,
    UnknownPlatform,
    UnknownSession,
)
from agents._security import (
    MAX_KEY_FILE_BYTES,
    SEALED_OVERHEAD,
    Handshake,
    KeyPair,
    OwnerBatches,
    SecurityPolicy,
    Session,
    SessionTable,
    TrustStore,
    WatchGate,
    _box_bytes,
    _box_bytes_std,
    _box_text,
    key_paths,
    read_public_key,
    seal_for_owner,
    sign_owner_batch,
    watch_answer,
    watch_request,
    watch_time,
)
from federation._cli_net import _WATCH_MARGIN, _WatchAnchor

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_795_000_000.0
ACL = orjson.dumps(
    {
        "v": 1,
        "performative": "request",
        "sender": "federation@uav-a",
        "receivers": ["federation@uav-b"],
        "content": {"action": "create-stream", "labels": ["heli-position"], "note": 'q"\\'},
        "protocol": "fipa-request",
        "conversation_id": "c-1-2",
    }
)


class Clock:
    """A settable clock shared by both platforms of a test."""

    def __init__(self, t: float = T0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t

    def advance(self, seconds: float) -> None:
        self.t += seconds


@dataclass
class Platform:
    keys: KeyPair
    trust: TrustStore
    hs: Handshake
    table: SessionTable


# These tests read the MAC-only envelope format; platforms encrypt by default, and the
# tests of the encrypted form say encrypt=True.
MacPolicy = functools.partial(SecurityPolicy, encrypt=False)

KEYS = {name: KeyPair.generate(name) for name in ("uav-a", "uav-b", "uav-c")}


def make_platform(
    name: str,
    clock: Clock,
    policy: SecurityPolicy | None = None,
    trusted: tuple[str, ...] = ("uav-a", "uav-b"),
    federation: str = "demo",
) -> Platform:
    policy = policy or MacPolicy()
    trust = TrustStore(federation, {p: KEYS[p].public_key for p in trusted})
    return Platform(
        KEYS[name],
        trust,
        Handshake(KEYS[name], trust, policy=policy, clock=clock),
        SessionTable(name, trust, policy=policy, clock=clock),
    )


def connect(a: Platform, b: Platform) -> tuple[Session, Session]:
    """a initiates a handshake with b; both tables hold the session."""
    reply, sb = b.hs.respond(a.hs.initiate(b.keys.platform))
    sa = a.hs.finish(reply)
    a.table.add(sa)
    b.table.add(sb)
    return sa, sb


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def pair(clock: Clock) -> tuple[Platform, Platform]:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    return a, b


def edit(envelope: bytes, **changes: object) -> bytes:
    obj = orjson.loads(envelope)
    obj.update(changes)
    return orjson.dumps(obj)


# --------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("encrypt", [False, True])
def test_round_trip_both_directions(clock: Clock, encrypt: bool) -> None:
    policy = MacPolicy(encrypt=encrypt)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    sa, sb = connect(a, b)
    assert sa.sid == sb.sid and sa.initiator and not sb.initiator
    for i in range(3):
        assert b.table.open(a.table.seal("uav-b", ACL)) == ("uav-a", ACL)
        assert a.table.open(b.table.seal("uav-a", ACL + b" " * i)) == ("uav-b", ACL + b" " * i)
    env = orjson.loads(a.table.seal("uav-b", ACL))
    assert env["from"] == "uav-a" and env["to"] == "uav-b" and env["n"] == 4
    assert ("box" in env) is encrypt and ("body" in env) is not encrypt
    if not encrypt:
        assert env["body"] == ACL.decode()  # readable by plain tools
    assert sa.sent == 4 and sb.received == 3


def test_seal_accepts_str_and_refuses_oversize(pair: tuple[Platform, Platform]) -> None:
    a, b = pair
    assert b.table.open(a.table.seal("uav-b", ACL.decode())) == ("uav-a", ACL)
    with pytest.raises(MessageError, match="exceeds"):
        a.table.seal("uav-b", b'"' + b"x" * 300_000 + b'"')


def test_direction_keys_differ_and_reflection_is_refused(pair: tuple[Platform, Platform]) -> None:
    a, _ = pair
    env = a.table.seal("uav-b", ACL)
    with pytest.raises(Misdirected):
        a.table.open(env)  # reflected back to its sender
    with pytest.raises(Forged):
        # even relabelled as coming from b, a's own sending key is not b's
        a.table.open(edit(env, **{"from": "uav-b", "to": "uav-a"}))


# --------------------------------------------------------------------------- refusals


def test_forged_mac(pair: tuple[Platform, Platform]) -> None:
    a, b = pair
    env = a.table.seal("uav-b", ACL)
    fake = base64.b64encode(os.urandom(32)).decode()
    with pytest.raises(Forged) as info:
        b.table.open(edit(env, mac=fake))
    assert info.value.code == "forged" and info.value.platform == "uav-a"


def test_tampered_body(pair: tuple[Platform, Platform]) -> None:
    a, b = pair
    env = a.table.seal("uav-b", ACL)
    body = orjson.loads(env)["body"].replace("heli-position", "heli-positioN")
    with pytest.raises(Forged):
        b.table.open(edit(env, body=body))


@pytest.mark.parametrize(
    ("field", "value", "error"),
    [
        ("ts_ms", int(T0 * 1000) + 1, Forged),
        ("n", 7, Forged),
        ("sid", "AAAAAAAAAAAAAAAAAAAAAA", UnknownSession),
        ("to", "uav-c", Misdirected),
        ("from", "uav-c", UnknownPlatform),
        ("v", 2, Malformed),
    ],
)
def test_tampered_header_field(
    pair: tuple[Platform, Platform], field: str, value: object, error: type[Exception]
) -> None:
    a, b = pair
    env = a.table.seal("uav-b", ACL)
    with pytest.raises(error):
        b.table.open(edit(env, **{field: value}))
    assert b.table.open(env) == ("uav-a", ACL)


def test_from_of_another_trusted_platform_is_forged(clock: Clock) -> None:
    trusted = ("uav-a", "uav-b", "uav-c")
    a, b, c = (make_platform(p, clock, trusted=trusted) for p in ("uav-a", "uav-b", "uav-c"))
    connect(a, b)
    connect(c, b)
    env = a.table.seal("uav-b", ACL)
    with pytest.raises(Forged, match="belongs to 'uav-a'"):
        b.table.open(edit(env, **{"from": "uav-c"}))


def test_replay(pair: tuple[Platform, Platform]) -> None:
    a, b = pair
    env = a.table.seal("uav-b", ACL)
    b.table.open(env)
    with pytest.raises(Replayed, match="already seen"):
        b.table.open(env)


def test_reorder_within_window_accepted_outside_refused(clock: Clock) -> None:
    policy = MacPolicy(window=64)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    envs = [a.table.seal("uav-b", ACL) for _ in range(200)]
    order = [*range(10, 0, -1), 0, *range(11, 70)]  # the first eleven arrive backwards
    for i in order:
        assert b.table.open(envs[i])[0] == "uav-a"
    for i in order:
        with pytest.raises(Replayed):
            b.table.open(envs[i])
    b.table.open(envs[150])  # a jump forward: 70..85 are now older than the window
    with pytest.raises(Replayed, match="older than the replay window"):
        b.table.open(envs[85])
    b.table.open(envs[87])  # 150 - 86 < 64: still inside
    b.table.open(envs[149])


@pytest.mark.parametrize("offset", [-31.0, 31.0])
def test_expired_timestamp(pair: tuple[Platform, Platform], clock: Clock, offset: float) -> None:
    a, b = pair
    env = a.table.seal("uav-b", ACL)
    clock.advance(-offset)  # the receiver's clock is 31 s ahead of / behind the sender's
    with pytest.raises(Expired, match="allowed ±30 s"):
        b.table.open(env)


def test_skew_is_configurable(clock: Clock) -> None:
    policy = MacPolicy(skew=5.0)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    env = a.table.seal("uav-b", ACL)
    clock.advance(4.9)
    b.table.open(env)
    env = a.table.seal("uav-b", ACL)
    clock.advance(5.1)
    with pytest.raises(Expired):
        b.table.open(env)


def test_unknown_session(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    sa, _ = connect(a, b)
    b2 = make_platform("uav-b", clock)  # b restarted: its sessions are gone
    with pytest.raises(UnknownSession) as info:
        b2.table.open(sa.seal(ACL))
    assert info.value.platform == "uav-a"
    with pytest.raises(UnknownSession, match="run a handshake first"):
        b2.table.seal("uav-a", ACL)


def test_untrusted_platform_and_revocation(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    env = a.table.seal("uav-b", ACL)
    b.trust.remove("uav-a")  # removal from the trust store revokes live sessions at once
    with pytest.raises(UnknownPlatform):
        b.table.open(env)


def test_a_session_of_a_key_no_longer_trusted_seals_nothing(clock: Clock) -> None:
    """Sealing checks the session's key as opening does: by identity, then by value (a
    handshake may verify with another store holding the same keys)."""
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    b.table.open(a.table.seal("uav-b", ACL))
    assert a.table.session_for("uav-b") is not None
    assert a.trust.add("uav-b", KeyPair.generate("uav-x").public_key, replace=True)
    assert a.table.session_for("uav-b") is None  # re-keyed: none to seal with
    with pytest.raises(UnknownSession, match="run a handshake first"):
        a.table.seal("uav-b", ACL)
    with pytest.raises(UnknownSession, match="run a handshake first"):
        a.table.seal_bytes("uav-b", b"x")
    # the agreed key back, in another key object (as another store holds it): by value
    assert a.trust.add("uav-b", KEYS["uav-b"].public_key, replace=True)
    b.table.open(a.table.seal("uav-b", ACL))
    a.trust.remove("uav-b")
    with pytest.raises(UnknownSession):
        a.table.seal("uav-b", ACL)


def test_removing_a_platform_tells_each_callback_once(
    clock: Clock, caplog: pytest.LogCaptureFixture
) -> None:
    b = make_platform("uav-b", clock)
    told: list[str] = []

    def broken(platform: str) -> None:
        raise RuntimeError("a broken callback")

    b.trust.on_remove(broken)
    unhook = b.trust.on_remove(told.append)
    b.trust.add("uav-c", KeyPair.generate("uav-c").public_key)
    assert b.trust.remove("uav-c")
    assert not b.trust.remove("uav-c")  # no longer trusted: nothing to tell
    assert not b.trust.remove("nobody")
    assert told == ["uav-c"]  # told though a callback before it failed
    assert "uav-c" not in b.trust  # revoked all the same, the failure logged
    assert "a callback on removing 'uav-c' failed" in caplog.text
    unhook()
    unhook()  # twice: nothing more
    b.trust.add("uav-c", KeyPair.generate("uav-c").public_key)
    assert b.trust.remove("uav-c")
    assert told == ["uav-c"]


def test_a_trust_or_key_file_that_is_no_regular_file_or_too_large_is_refused_at_once(
    tmp_path: Path,
) -> None:
    """A FIFO in the file's place is refused without blocking the read (the file opened is
    checked, not its name), and so is a file larger than any trust file could be."""
    trust = TrustStore("demo", {"uav-a": KeyPair.generate("uav-a").public_key})
    path = tmp_path / "trust.json"
    os.mkfifo(path, 0o600)  # a read of it would wait for a writer for ever
    started = time.monotonic()
    with pytest.raises(KeyFileError, match="the trust file is not a regular file"):
        TrustStore.load(path)
    assert time.monotonic() - started < 5
    path.unlink()
    data = trust.to_json()
    path.write_bytes(data[:-1] + b" " * (MAX_KEY_FILE_BYTES + 1) + data[-1:])
    path.chmod(0o600)
    with pytest.raises(KeyFileError, match=f"larger than {MAX_KEY_FILE_BYTES} bytes"):
        TrustStore.load(path)
    path.write_bytes(data)  # the same content, no larger: read
    assert set(TrustStore.load(path)) == {"uav-a"}
    key = tmp_path / "uav-a.pub.json"
    os.mkfifo(key, 0o600)
    with pytest.raises(KeyFileError, match="the public key file is not a regular file"):
        read_public_key(key)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"not json", "not JSON"),
        (b"[1, 2]", "JSON object"),
        (b'{"v": 1}', "missing"),
        (b"x" * 600_000, "exceeds"),
    ],
)
def test_malformed(pair: tuple[Platform, Platform], data: bytes, match: str) -> None:
    _, b = pair
    with pytest.raises(Malformed, match=match):
        b.table.open(data)


@pytest.mark.parametrize(
    "changes",
    [{"n": 0}, {"n": True}, {"n": -1}, {"ts_ms": 1.5}, {"body": 5}, {"mac": None}, {"x": 1}],
)
def test_malformed_fields(pair: tuple[Platform, Platform], changes: dict[str, object]) -> None:
    a, b = pair
    with pytest.raises(Malformed):
        b.table.open(edit(a.table.seal("uav-b", ACL), **changes))


def test_require_encryption_refuses_plain(clock: Clock) -> None:
    a = make_platform("uav-a", clock)
    b = make_platform("uav-b", clock, MacPolicy(require_encryption=True))
    connect(a, b)
    with pytest.raises(Malformed, match="requires encrypted"):
        b.table.open(a.table.seal("uav-b", ACL))


def test_the_default_policy_encrypts_and_refuses_plain_envelopes(clock: Clock) -> None:
    """Platforms encrypt by default; a plain envelope is refused as 'unencrypted'."""
    assert SecurityPolicy().encrypt and SecurityPolicy().require_encryption
    assert not SecurityPolicy(encrypt=False).require_encryption  # debugging: both forms
    assert SecurityPolicy(encrypt=False, require_encryption=True).require_encryption
    plain = make_platform("uav-a", clock)  # MAC-only
    b = make_platform("uav-b", clock, SecurityPolicy())
    connect(plain, b)
    with pytest.raises(Unencrypted, match="requires encrypted") as info:
        b.table.open(plain.table.seal("uav-b", ACL))
    assert info.value.code == "unencrypted" and info.value.platform == "uav-a"
    with pytest.raises(Unencrypted):
        b.table.open_bytes(plain.table.seal_bytes("uav-b", b"batch"))
    a = make_platform("uav-a", clock, SecurityPolicy())
    b = make_platform("uav-b", clock, SecurityPolicy())
    connect(a, b)
    env = a.table.seal("uav-b", ACL)
    assert b"box" in env and ACL not in env and b"performative" not in env
    assert b.table.open(env) == ("uav-a", ACL)


def test_sealed_for_the_owner_opens_with_the_owners_key_only() -> None:
    """What a platform seals for its owner (the audit, the watch) opens with its key only."""
    owner, other = KeyPair.generate("uav-a"), KeyPair.generate("uav-a")
    box = seal_for_owner(owner.public_key, b'{"verdict":"accepted"}\n')
    assert b"verdict" not in box and len(box) == len(b'{"verdict":"accepted"}\n') + SEALED_OVERHEAD
    assert owner.open_sealed(box) == b'{"verdict":"accepted"}\n'
    for bad in (box[:-1] + bytes([box[-1] ^ 1]), box[:20], b""):
        with pytest.raises(Forged):
            owner.open_sealed(bad)
    with pytest.raises(Forged):
        other.open_sealed(box)


def _owner_batch(platform: KeyPair, key: str, data: bytes, at: float) -> bytes:
    """``data`` as ``platform`` publishes it for its owner on ``key`` at ``at`` (POSIX s)."""
    return seal_for_owner(
        platform.public_key, sign_owner_batch(platform, key, data, int(at * 1000))
    )


def test_the_owner_refuses_a_batch_signed_before_it_began_listening(clock: Clock) -> None:
    """A batch signed by the platform within the skew, never seen here, is still refused when
    it was signed before this side began listening (recorded and replayed); one signed since
    is taken once, in whatever order it comes (a platform clock stepped back stalls nothing)."""
    platform = KeyPair.generate("uav-a")
    audit = "dyknow/demo/v1/audit/uav-a"
    before = _owner_batch(platform, audit, b"{}\n", clock() - 2)  # recorded before
    owner = OwnerBatches(platform, platform.public_key, clock=clock, since=clock() - 1)
    with pytest.raises(Replayed, match="before this side began reading"):
        owner.open(audit, before)
    late = _owner_batch(platform, audit, b'{"n":1}\n', clock() + 1)  # delayed on the way
    assert owner.open(audit, _owner_batch(platform, audit, b'{"n":2}\n', clock() + 2))
    stepped = _owner_batch(platform, audit, b'{"n":3}\n', clock() - 0.5)  # its clock stepped back
    assert owner.open(audit, stepped) == b'{"n":3}\n'
    assert owner.open(audit, late) == b'{"n":1}\n'
    with pytest.raises(Replayed, match="seen before"):
        owner.open(audit, late)
    clock.advance(32)
    with pytest.raises(Expired):  # forgotten only once outside the skew
        owner.open(audit, late)


def test_a_watch_answer_carries_the_platforms_time_signed_for_that_request(clock: Clock) -> None:
    """The answer's time verifies only with the platform's key over the request it answers:
    anyone answering in its place, or replaying an earlier answer, is refused; a bare
    answer (an older release) is told apart (None)."""
    owner = KeyPair.generate("uav-a")
    gate = WatchGate(owner, "demo", clock=clock)
    request = watch_request(owner, "demo", clock=clock)
    nonce = gate.check(request)
    answer = watch_answer(owner, "demo", nonce, 10.0, clock=lambda: clock() + 20)
    assert orjson.loads(answer)["lease_s"] == 10.0
    assert watch_time(owner.public_key, "demo", request, answer) == clock() + 20
    another = watch_request(owner, "demo", clock=clock)
    with pytest.raises(Forged):  # an answer to another request: replayed
        watch_time(owner.public_key, "demo", another, answer)
    with pytest.raises(Forged):  # signed by anyone else
        watch_time(
            owner.public_key, "demo", request, watch_answer(KEYS["uav-b"], "demo", nonce, 10.0)
        )
    with pytest.raises(Forged):  # another federation's
        watch_time(owner.public_key, "other", request, answer)
    bare = b'{"v":1,"watching":true,"lease_s":10.0}'
    assert watch_time(owner.public_key, "demo", request, bare) is None
    wrong = answer.replace(b'"ts_ms"', b'"ts"')
    for junk in (b"", b"[]", b'{"watching":false}', wrong, b'{"watching":true,"x":"' + b"x" * 5000):
        with pytest.raises(Malformed):
            watch_time(owner.public_key, "demo", request, junk)
    fields = orjson.loads(answer)
    # each field's type and range is checked before the transcript is packed
    for change in (
        {"ts_ms": -1},
        {"ts_ms": 2**63},
        {"ts_ms": 1.0},
        {"ts_ms": True},
        {"ts_ms": "1"},
        {"v": 2},
        {"v": True},
        {"lease_s": 0},
        {"lease_s": "10"},
        {"sig": fields["sig"].rstrip("=")},
        {"sig": 5},
        {"extra": 1},
    ):
        junk = json.dumps(fields | change).encode()
        with pytest.raises(Malformed):
            watch_time(owner.public_key, "demo", request, junk)


@pytest.mark.parametrize("offset", [20.0, -3.0])
def test_the_watch_bounds_batches_on_the_platforms_clock_whatever_the_offset(
    clock: Clock, offset: float
) -> None:
    """Platform ahead by 20 s: a batch recorded 15 s before the watch began is refused.
    Platform behind by 3 s: its fresh batches are taken. The bound is the platform's time,
    signed into its answer, less the time since this side began listening."""
    platform = KeyPair.generate("uav-a")
    audit = "dyknow/demo/v1/audit/uav-a"
    began = clock() + offset  # the platform's clock when the watch began listening
    recorded = _owner_batch(platform, audit, b"{}\n", began - 15)
    owner = OwnerBatches(platform, platform.public_key, clock=clock)
    anchor = _WatchAnchor(owner, listening=100.0, skew=30.0)
    anchor.answered(began + 0.15, asked=100.1, received=100.2)  # signed in between
    with pytest.raises(Replayed, match="before this side began reading"):
        owner.open(audit, recorded)
    fresh = b'{"n":1}\n'
    assert owner.open(audit, _owner_batch(platform, audit, fresh, began + 0.3)) == fresh
    assert owner.open(audit, _owner_batch(platform, audit, fresh, began - 0.1)) == fresh


def test_a_platform_clock_stepped_back_is_followed_at_the_next_renewal(clock: Clock) -> None:
    """The platform's clock steps back 5 s a second into the watch: its batches are refused
    (shown, counted) until the next renewal's signed time shows the step; then taken, while
    one recorded long before the watch stays refused. Its jitter never lowers the bound."""
    platform = KeyPair.generate("uav-a")
    audit = "dyknow/demo/v1/audit/uav-a"
    owner = OwnerBatches(platform, platform.public_key, clock=clock)
    anchor = _WatchAnchor(owner, listening=0.0, skew=30.0)
    began = clock()
    anchor.answered(began + 0.1, asked=0.05, received=0.2)
    since = owner.since
    anchor.answered(began + 3.05, asked=3.0, received=4.9)  # a slow answer: no step
    assert owner.since == since
    stepped = _owner_batch(platform, audit, b'{"n":1}\n', began + 1.2 - 5)
    with pytest.raises(Replayed, match="stepped back"):
        owner.open(audit, stepped)
    anchor.answered(began + 6.05 - 5, asked=6.0, received=6.1)
    assert owner.open(audit, _owner_batch(platform, audit, b'{"n":2}\n', began + 6.2 - 5))
    with pytest.raises(Replayed):
        owner.open(audit, _owner_batch(platform, audit, b"{}\n", began - 15))


def test_a_bare_watch_answer_falls_back_to_this_clock_less_the_allowance(clock: Clock) -> None:
    """A platform of an older release answers bare: the bound is this side's clock less the
    federation's clock allowance; a signed answer later (the platform's) tightens it."""
    owner = OwnerBatches(KEYS["uav-a"], KEYS["uav-a"].public_key, clock=clock)
    anchor = _WatchAnchor(owner, listening=0.0, skew=30.0)
    before = time.time()
    anchor.answered(None, asked=0.0, received=0.5)
    assert owner.since is not None and before - 31 < owner.since < time.time() - 30
    anchor.answered(clock() + 3.1, asked=3.0, received=3.2)
    assert owner.since == pytest.approx(clock() + 3.1 - 3.2 - _WATCH_MARGIN)


def test_watch_requests_are_signed_fresh_and_used_once(clock: Clock) -> None:
    """Only the platform's own key asks to watch it; a replayed or stale request is refused."""
    owner = KeyPair.generate("uav-a")
    gate = WatchGate(owner, "demo", clock=clock)
    req = watch_request(owner, "demo", clock=clock)
    gate.check(req)
    with pytest.raises(Replayed):
        gate.check(req)
    with pytest.raises(Forged):  # the right name, another key: a member, or an outsider
        gate.check(watch_request(KeyPair.generate("uav-a"), "demo", clock=clock))
    with pytest.raises(Misdirected):
        gate.check(watch_request(owner, "other", clock=clock))
    with pytest.raises(Misdirected):
        gate.check(watch_request(KEYS["uav-b"], "demo", clock=clock))
    stale = watch_request(owner, "demo", clock=lambda: clock() - 31)
    with pytest.raises(Expired):
        gate.check(stale)
    for junk in (b"", b"[]", b'{"v": 1}', b"x" * 5000):
        with pytest.raises(Malformed):
            gate.check(junk)


@pytest.mark.parametrize("encrypt", [False, True])
def test_any_flipped_byte_is_refused(encrypt: bool) -> None:
    clock = Clock()
    policy = MacPolicy(encrypt=encrypt)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    env = a.table.seal("uav-b", ACL)

    @given(index=st.integers(0, len(env) - 1), mask=st.integers(1, 255))
    def flipped(index: int, mask: int) -> None:
        bad = bytearray(env)
        bad[index] ^= mask
        with pytest.raises(AuthenticationError):
            b.table.open(bytes(bad))

    flipped()
    assert b.table.open(env) == ("uav-a", ACL)  # the refusals left the session intact


# --------------------------------------------------------------------------- handshake


def test_handshake_from_unknown_platform(clock: Clock) -> None:
    c = make_platform("uav-c", clock, trusted=("uav-b", "uav-c"))
    b = make_platform("uav-b", clock)  # does not trust uav-c
    with pytest.raises(UnknownPlatform, match="uav-c"):
        b.hs.respond(c.hs.initiate("uav-b"))
    a = make_platform("uav-a", clock)
    with pytest.raises(UnknownPlatform):
        a.hs.initiate("uav-c")


def test_handshake_signed_by_key_not_in_trust_file(clock: Clock) -> None:
    # an impostor with its own key claims to be uav-a
    impostor_keys = KeyPair.generate("uav-a")
    trust = TrustStore(
        "demo", {"uav-a": impostor_keys.public_key, "uav-b": KEYS["uav-b"].public_key}
    )
    impostor = Handshake(impostor_keys, trust, clock=clock)
    b = make_platform("uav-b", clock)
    with pytest.raises(Forged, match="signature"):
        b.hs.respond(impostor.initiate("uav-b"))
    # and a reply signed by an impostor of uav-b is refused by a real initiator
    a = make_platform("uav-a", clock)
    fake_b = Handshake(
        KeyPair.generate("uav-b"),
        TrustStore("demo", {"uav-a": KEYS["uav-a"].public_key}),
        clock=clock,
    )
    reply, _ = fake_b.respond(a.hs.initiate("uav-b"))
    with pytest.raises(Forged):
        a.hs.finish(reply)


@pytest.mark.parametrize("field", ["epk", "nonce", "ts_ms", "sig"])
def test_handshake_tampered_request(clock: Clock, field: str) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    req = orjson.loads(a.hs.initiate("uav-b"))
    if field == "ts_ms":
        req[field] += 1
    else:
        raw = bytearray(base64.b64decode(req[field]))
        raw[0] ^= 1
        req[field] = base64.b64encode(bytes(raw)).decode()
    with pytest.raises(Forged):
        b.hs.respond(orjson.dumps(req))


def test_handshake_tampered_reply(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    reply, _ = b.hs.respond(a.hs.initiate("uav-b"))
    obj = orjson.loads(reply)
    obj["epk"] = base64.b64encode(os.urandom(32)).decode()
    with pytest.raises(Forged):
        a.hs.finish(orjson.dumps(obj))
    assert a.hs.finish(reply).peer == "uav-b"  # the genuine reply still works


def test_handshake_stale_timestamp(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    req = a.hs.initiate("uav-b")
    clock.advance(31)
    with pytest.raises(Expired):
        b.hs.respond(req)
    req = a.hs.initiate("uav-b")
    reply, _ = b.hs.respond(req)
    clock.advance(31)
    with pytest.raises(Expired):
        a.hs.finish(reply)


def test_handshake_wrong_federation(clock: Clock) -> None:
    a = make_platform("uav-a", clock, federation="other")
    b = make_platform("uav-b", clock)
    with pytest.raises(Misdirected, match="federation 'other'"):
        b.hs.respond(a.hs.initiate("uav-b"))


def test_handshake_wrong_addressee(clock: Clock) -> None:
    trusted = ("uav-a", "uav-b", "uav-c")
    a = make_platform("uav-a", clock, trusted=trusted)
    c = make_platform("uav-c", clock, trusted=trusted)
    with pytest.raises(Misdirected, match="for 'uav-b' reached 'uav-c'"):
        c.hs.respond(a.hs.initiate("uav-b"))
    # a genuine reply of c, to a request for c, does not finish a handshake with b
    req_b = orjson.loads(a.hs.initiate("uav-b"))
    req_c = orjson.loads(a.hs.initiate("uav-c"))
    reply_c = orjson.loads(c.hs.respond(orjson.dumps(req_c))[0])
    reply_c["re"] = req_b["nonce"]
    with pytest.raises(Forged, match="handshake with 'uav-b'"):
        a.hs.finish(orjson.dumps(reply_c))


def test_handshake_replayed(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    req = a.hs.initiate("uav-b")
    reply, _ = b.hs.respond(req)
    with pytest.raises(Replayed, match="already answered"):
        b.hs.respond(req)
    a.hs.finish(reply)
    with pytest.raises(Replayed, match="already used"):
        a.hs.finish(reply)
    with pytest.raises(UnknownSession, match="no request of ours"):
        make_platform("uav-a", clock).hs.finish(reply)


@pytest.mark.parametrize(
    "data",
    [b"{", b"[]", b'{"v":1,"kx":"init"}', b'{"v":2}', b"x" * 5000],
)
def test_handshake_malformed(clock: Clock, data: bytes) -> None:
    b = make_platform("uav-b", clock)
    with pytest.raises(Malformed):
        b.hs.respond(data)
    with pytest.raises(Malformed):
        b.hs.finish(data)


def test_handshake_request_is_not_a_reply(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    with pytest.raises(Malformed):
        a.hs.finish(a.hs.initiate("uav-b"))
    with pytest.raises(Malformed):
        a.hs.respond(b.hs.respond(a.hs.initiate("uav-b"))[0])


def test_handshake_federation_argument_must_match_trust_file() -> None:
    trust = TrustStore("demo")
    assert Handshake(KEYS["uav-a"], trust, "demo").federation == "demo"
    with pytest.raises(ValueError, match="differs"):
        Handshake(KEYS["uav-a"], trust, "other")


def test_simultaneous_handshakes_converge(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    req_a, req_b = a.hs.initiate("uav-b"), b.hs.initiate("uav-a")
    clock.advance(0.001)
    reply_b, s1_b = b.hs.respond(req_a)
    reply_a, s2_a = a.hs.respond(req_b)
    b.table.add(s1_b)
    a.table.add(s2_a)
    a.table.add(a.hs.finish(reply_b))
    b.table.add(b.hs.finish(reply_a))
    for _ in range(3):
        assert b.table.open(a.table.seal("uav-b", ACL))[0] == "uav-a"
        assert a.table.open(b.table.seal("uav-a", ACL))[0] == "uav-b"
    clock.advance(31)  # past any grace: whatever they settled on still works
    assert b.table.open(a.table.seal("uav-b", ACL))[0] == "uav-a"
    assert a.table.open(b.table.seal("uav-a", ACL))[0] == "uav-b"


# --------------------------------------------------------------------------- renewal


def test_renewal_after_messages(clock: Clock) -> None:
    policy = MacPolicy(renew_after_messages=5)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    sa, _ = connect(a, b)
    for _ in range(4):
        a.table.seal("uav-b", ACL)
    assert not sa.needs_renewal() and not a.table.needs_renewal("uav-b")
    a.table.seal("uav-b", ACL)
    assert sa.needs_renewal() and a.table.needs_renewal("uav-b")
    clock.advance(0.01)
    sa2, _ = connect(a, b)
    assert not a.table.needs_renewal("uav-b")
    assert a.table.session_for("uav-b") is sa2


def test_renewal_after_time_and_grace(clock: Clock) -> None:
    policy = MacPolicy(renew_after_seconds=100, grace=10)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    sa1, sb1 = connect(a, b)
    assert not sb1.confirmed
    b.table.open(a.table.seal("uav-b", ACL))  # a has used the session: b may use it too
    assert sb1.confirmed and not a.table.needs_renewal("uav-b")
    clock.advance(100)
    assert sa1.needs_renewal() and a.table.needs_renewal("uav-b")
    assert not sb1.needs_renewal()  # the responder leaves the first move to the initiator
    late = sa1.seal(ACL)  # sealed on the old session, still in flight
    sa2, sb2 = connect(a, b)
    assert a.table.session_for("uav-b") is sa2
    # b has not heard from a on the new session yet: it keeps sending on the old one
    assert b.table.session_for("uav-a") is sb1
    assert b.table.open(a.table.seal("uav-b", ACL))[0] == "uav-a"
    assert b.table.session_for("uav-a") is sb2  # now b knows a holds the new session
    clock.advance(5)
    assert b.table.open(late)[0] == "uav-a"  # old session within grace
    late = sa1.seal(ACL)
    clock.advance(6)
    with pytest.raises(Expired, match="grace period is over"):
        b.table.open(late)
    assert a.table.open(b.table.seal("uav-a", ACL))[0] == "uav-b"
    assert b.table.prune() == 1 and b.table.sessions("uav-a") == [sb2]


def test_session_lifetime(clock: Clock) -> None:
    policy = MacPolicy(renew_after_seconds=100, grace=10)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    sa, _ = connect(a, b)
    clock.advance(105)
    env = sa.seal(ACL)  # 105 s old: renewal is due, but the session is still usable
    clock.advance(6)
    with pytest.raises(Expired, match="lifetime"):
        sa.seal(ACL)
    assert a.table.session_for("uav-b") is None and a.table.needs_renewal("uav-b")
    with pytest.raises(Expired, match="lifetime"):
        b.table.open(env)


def test_sessions_per_peer_are_capped(clock: Clock) -> None:
    policy = MacPolicy(max_sessions_per_peer=2)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    first, _ = connect(a, b)
    for _ in range(3):
        clock.advance(0.01)
        connect(a, b)
    assert len(a.table.sessions("uav-b")) == 2 and len(b.table) == 2
    with pytest.raises(UnknownSession):
        b.table.open(first.seal(ACL))


def test_forget(pair: tuple[Platform, Platform]) -> None:
    a, b = pair
    env = a.table.seal("uav-b", ACL)
    assert b.table.forget("uav-a") == 1
    assert b.table.forget("uav-a") == 0
    assert b.table.peers() == [] and b.table.session_for("uav-a") is None
    with pytest.raises(UnknownSession):
        b.table.open(env)
    a.hs.initiate("uav-b")
    assert a.hs.cancel("uav-b") == 1


def test_doubt_keeps_the_sessions_but_seals_on_none_until_the_peer_sends(
    clock: Clock,
) -> None:
    # a's token first seen by b: b's session with a may be a previous process's of a
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    sb, sa = connect(b, a)  # b initiated it: b seals on it at once
    assert b.table.session_for("uav-a") is sb
    assert b.table.doubt("uav-a") == 1 and b.table.doubt("uav-a") == 0
    assert b.table.peers() == ["uav-a"] and b.table.session_for("uav-a") is None
    with pytest.raises(UnknownSession):
        b.table.seal("uav-a", ACL)
    assert b.table.needs_renewal("uav-a")
    # a sends on it (a's current process after all): it opens, and b seals on it again
    assert b.table.open(sa.seal(ACL)) == ("uav-a", ACL)
    assert b.table.session_for("uav-a") is sb
    # doubted again, a new handshake makes the session to seal with; the old one still opens
    b.table.doubt("uav-a")
    clock.advance(0.01)
    sb2, _ = connect(b, a)
    assert b.table.session_for("uav-a") is sb2
    assert b.table.open(sa.seal(ACL)) == ("uav-a", ACL)


def test_table_refuses_foreign_or_duplicate_session(pair: tuple[Platform, Platform]) -> None:
    a, b = pair
    (sa,) = a.table.sessions("uav-b")
    with pytest.raises(ValueError, match="already"):
        a.table.add(sa)
    with pytest.raises(ValueError, match="table of 'uav-b'"):
        b.table.add(sa)


# --------------------------------------------------------------------------- key files


def test_key_files(tmp_path: Path) -> None:
    pair = KeyPair.generate("uav-a")
    key_path, pub_path = pair.save(tmp_path / "keys")
    assert (key_path, pub_path) == key_paths(tmp_path / "keys", "uav-a")
    assert stat.S_IMODE(key_path.stat().st_mode) == 0o600
    assert stat.S_IMODE(pub_path.stat().st_mode) == 0o644
    loaded = KeyPair.load(key_path)
    assert loaded.platform == "uav-a" and loaded.public_key == pair.public_key
    assert read_public_key(pub_path) == ("uav-a", pair.public_key)
    with pytest.raises(KeyFileError, match="not overwriting"):
        KeyPair.generate("uav-a").save(tmp_path / "keys")
    assert KeyPair.load(key_path).public_key == pair.public_key
    other = KeyPair.generate("uav-a")
    other.save(tmp_path / "keys", force=True)
    assert KeyPair.load(key_path).public_key == other.public_key
    assert stat.S_IMODE(key_path.stat().st_mode) == 0o600
    assert sorted(p.name for p in (tmp_path / "keys").iterdir()) == ["uav-a.key", "uav-a.pub"]


def test_private_key_readable_by_others_is_refused(tmp_path: Path) -> None:
    key_path, _ = KeyPair.generate("uav-a").save(tmp_path)
    key_path.chmod(0o644)
    with pytest.raises(KeyFileError, match="chmod 600"):
        KeyPair.load(key_path)


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("{", "not JSON"),
        (
            '{"v":1,"kind":"dyknow-ed25519-private","platform":"uav-a","ed25519_seed":"AAAA"}',
            "key 'ed25519_seed'",
        ),
        (
            '{"v":1,"kind":"dyknow-ed25519-private","platform":"a b","ed25519_seed":""}',
            "key 'platform'",
        ),
        ('{"v":1,"kind":"dyknow-ed25519-public"}', "key 'kind'"),
        ('{"v":9}', "key 'v'"),
    ],
)
def test_private_key_file_errors(tmp_path: Path, content: str, match: str) -> None:
    path = tmp_path / "x.key"
    path.write_text(content)
    path.chmod(0o600)
    with pytest.raises(KeyFileError, match=match) as info:
        KeyPair.load(path)
    assert str(path) in str(info.value)


def test_trust_store_round_trip(tmp_path: Path) -> None:
    store = TrustStore("demo")
    assert store.add("uav-a", KEYS["uav-a"].public_key)
    assert not store.add("uav-a", KEYS["uav-a"].public_key)
    with pytest.raises(ValueError, match="already trusted with another key"):
        store.add("uav-a", KEYS["uav-b"].public_key)
    assert store.add("uav-b", KEYS["uav-b"].public_key)
    store.save(tmp_path / "trust.json")
    loaded = TrustStore.load(tmp_path / "trust.json")
    assert loaded.federation == "demo" and list(loaded) == ["uav-a", "uav-b"]
    assert loaded.public_key("uav-b") == KEYS["uav-b"].public_key
    assert store.add("uav-a", KEYS["uav-c"].public_key, replace=True)
    assert store.remove("uav-a") and not store.remove("uav-a") and "uav-a" not in store
    with pytest.raises(UnknownPlatform):
        store.verify_key("uav-a")


GOOD_KEY = base64.b64encode(KEYS["uav-a"].public_key).decode()


@pytest.mark.parametrize(
    ("content", "match"),
    [
        ("", "not JSON"),
        ("[]", "JSON object"),
        ('{"v":2,"federation":"demo","platforms":{}}', "key 'v'"),
        ('{"v":1,"platforms":{}}', "key 'federation'"),
        ('{"v":1,"federation":"de mo","platforms":{}}', "key 'federation'"),
        ('{"v":1,"federation":"demo"}', "key 'platforms'"),
        ('{"v":1,"federation":"demo","platforms":[]}', "key 'platforms'"),
        ('{"v":1,"federation":"demo","platforms":{},"extra":1}', "unexpected key 'extra'"),
        ('{"v":1,"federation":"demo","platforms":{"uav-b":"abc"}}', "key 'platforms.uav-b'"),
        ('{"v":1,"federation":"demo","platforms":{"uav-b":"AAAA"}}', "key 'platforms.uav-b'"),
        ('{"v":1,"federation":"demo","platforms":{"uav-b":5}}', "key 'platforms.uav-b'"),
        # named: the key is made at import, and an id from it would differ between the
        # processes of a parallel run, which must all collect the same tests
        pytest.param(
            f'{{"v":1,"federation":"demo","platforms":{{"u/x":"{GOOD_KEY}"}}}}',
            "key 'platforms.u/x'",
            id="good-key-bad-name",
        ),
    ],
)
def test_trust_file_errors_name_file_and_key(tmp_path: Path, content: str, match: str) -> None:
    path = tmp_path / "trust.json"
    path.write_text(content)
    with pytest.raises(KeyFileError, match=match) as info:
        TrustStore.load(path)
    assert info.value.path == str(path) and str(path) in str(info.value)
    assert isinstance(info.value, SecurityError)


def test_trust_file_missing_or_world_writable(tmp_path: Path) -> None:
    with pytest.raises(KeyFileError, match="no such trust file"):
        TrustStore.load(tmp_path / "nope.json")
    path = tmp_path / "trust.json"
    TrustStore("demo", {"uav-a": KEYS["uav-a"].public_key}).save(path)
    path.chmod(0o666)
    with pytest.raises(KeyFileError, match="writable by others"):
        TrustStore.load(path)


def test_keys_cli(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from federation.cli import main

    def process(*args: str) -> subprocess.CompletedProcess[str]:
        """``dyknow keys ARGS`` as a user runs it: a process of its own."""
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        return subprocess.run(
            [sys.executable, "-m", "federation.cli", "keys", *args],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )

    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        """``dyknow keys ARGS`` in this process: the same code, without an interpreter's start.

        Each process took about a second to start (imports); one shows the entry point works.
        """
        code = main(["keys", *args])
        out = capsys.readouterr()
        return subprocess.CompletedProcess(["dyknow", "keys", *args], code, out.out, out.err)

    monkeypatch.chdir(tmp_path)
    for platform, run in (("uav-a", process), ("uav-b", cli)):
        done = run("gen", "--platform", platform, "--dir", "keys/")
        assert done.returncode == 0, done.stderr
        assert f"keys/{platform}.key" in done.stdout
    assert stat.S_IMODE((tmp_path / "keys/uav-a.key").stat().st_mode) == 0o600
    before = (tmp_path / "keys/uav-a.key").read_bytes()
    again = cli("gen", "--platform", "uav-a", "--dir", "keys/")
    assert again.returncode == 1 and "--force" in again.stderr
    assert (tmp_path / "keys/uav-a.key").read_bytes() == before

    missing = cli("trust", "--trust-file", "trust.json", "keys/uav-a.pub", "keys/uav-b.pub")
    assert missing.returncode == 1 and "--federation" in missing.stderr
    done = cli(
        "trust",
        "--trust-file",
        "trust.json",
        "--federation",
        "demo",
        "keys/uav-a.pub",
        "keys/uav-b.pub",
    )
    assert done.returncode == 0, done.stderr
    store = TrustStore.load(tmp_path / "trust.json")
    assert list(store) == ["uav-a", "uav-b"]
    assert store.public_key("uav-a") == KeyPair.load(tmp_path / "keys/uav-a.key").public_key

    assert cli("gen", "--platform", "uav-a", "--dir", "keys/", "--force").returncode == 0
    clash = cli("trust", "--trust-file", "trust.json", "keys/uav-a.pub")
    assert clash.returncode == 1 and "--replace" in clash.stderr
    assert cli("trust", "--trust-file", "trust.json", "--replace", "keys/uav-a.pub").returncode == 0
    assert cli("untrust", "--trust-file", "trust.json", "uav-b").returncode == 0
    shown = cli("show", "--trust-file", "trust.json")
    assert shown.returncode == 0 and "uav-a" in shown.stdout and "uav-b" not in shown.stdout


def test_keys_and_trust_file_drive_a_handshake(tmp_path: Path) -> None:
    from agents.keys import gen_keys, trust_keys

    gen_keys("uav-a", tmp_path)
    gen_keys("uav-b", tmp_path)
    trust_keys(
        tmp_path / "t.json", [tmp_path / "uav-a.pub", tmp_path / "uav-b.pub"], federation="demo"
    )
    trust = TrustStore.load(tmp_path / "t.json")
    clock = Clock()
    ha = Handshake(KeyPair.load(tmp_path / "uav-a.key"), trust, clock=clock)
    hb = Handshake(KeyPair.load(tmp_path / "uav-b.key"), trust, clock=clock)
    reply, sb = hb.respond(ha.initiate("uav-b"))
    table = SessionTable("uav-b", trust, clock=clock)
    table.add(sb)
    assert table.open(ha.finish(reply).seal(ACL)) == ("uav-a", ACL)


class Skewed(Clock):
    """Another platform's clock: the shared clock plus a fixed offset."""

    def __init__(self, base: Clock, offset: float) -> None:
        self.base, self.offset = base, offset

    def __call__(self) -> float:
        return self.base() + self.offset


def test_renewal_order_survives_clock_skew(clock: Clock) -> None:
    # b's clock runs 10 s ahead: a session b starts 5 s after a's must still count as newer
    a = make_platform("uav-a", clock)
    b = make_platform("uav-b", Skewed(clock, 10.0))
    s1_a, s1_b = connect(a, b)
    b.table.open(a.table.seal("uav-b", ACL))
    clock.advance(5)
    s2_b, s2_a = connect(b, a)
    assert s2_a.order > s1_a.order and s2_b.order > s1_b.order
    assert a.table.open(b.table.seal("uav-a", ACL))[0] == "uav-b"
    assert a.table.session_for("uav-b") is s2_a and b.table.session_for("uav-a") is s2_b
    assert not a.table.needs_renewal("uav-b") and not b.table.needs_renewal("uav-a")


def test_pending_handshake(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    assert not a.hs.pending("uav-b")
    request = a.hs.initiate("uav-b")
    assert a.hs.pending("uav-b") and not b.hs.pending("uav-a")
    a.hs.finish(b.hs.respond(request)[0])
    assert not a.hs.pending("uav-b")
    a.hs.initiate("uav-b")
    clock.advance(31)
    assert not a.hs.pending("uav-b")  # a lost request stops blocking a new one


def test_responder_does_not_send_first(clock: Clock) -> None:
    a, b = make_platform("uav-a", clock), make_platform("uav-b", clock)
    connect(a, b)
    assert b.table.session_for("uav-a") is None and b.table.needs_renewal("uav-a")
    with pytest.raises(UnknownSession):
        b.table.seal("uav-a", ACL)
    b.table.open(a.table.seal("uav-b", ACL))
    assert a.table.open(b.table.seal("uav-a", ACL))[0] == "uav-b"
    assert not b.table.needs_renewal("uav-a")


def test_replayed_requests_after_restart_cannot_evict_the_live_session(clock: Clock) -> None:
    policy = MacPolicy(max_sessions_per_peer=2)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    captured = [a.hs.initiate("uav-b") for _ in range(3)]
    live, _ = connect(a, b)
    b.table.open(live.seal(ACL))
    for request in captured:
        # each replay reaches a freshly restarted handshake state (its replay cache is empty)
        fresh = Handshake(KEYS["uav-b"], b.trust, policy=policy, clock=clock)
        b.table.add(fresh.respond(request)[1])
    assert live.sid in {s.sid for s in b.table.sessions("uav-a")}
    assert b.table.open(live.seal(ACL))[0] == "uav-a"
    assert b.table.session_for("uav-a") is not None


def test_simultaneous_renewals_keep_the_session_the_peer_is_about_to_use(clock: Clock) -> None:
    # both sides renew at once with room for two sessions: neither may evict the fresh
    # session the other just made and is about to seal on
    policy = MacPolicy(max_sessions_per_peer=2)
    a, b = make_platform("uav-a", clock, policy), make_platform("uav-b", clock, policy)
    connect(a, b)
    b.table.open(a.table.seal("uav-b", ACL))
    a.table.open(b.table.seal("uav-a", ACL))
    clock.advance(1)
    request_a = a.hs.initiate("uav-b")  # A starts a renewal ...
    clock.advance(1)
    connect(b, a)  # ... while B completes its own
    reply, s3 = b.hs.respond(request_a)
    b.table.add(s3)
    a.table.add(a.hs.finish(reply))
    assert a.table.open(b.table.seal("uav-a", ACL))[0] == "uav-b"
    assert b.table.open(a.table.seal("uav-b", ACL))[0] == "uav-a"


def test_the_aead_gives_libsodiums_bytes_and_refusals() -> None:
    """Sealing through `cryptography`: libsodium's bytes (nacl.bindings), and forgeries refused."""
    from nacl import bindings
    from nacl.exceptions import CryptoError

    from agents._security import _aead_decrypt, _aead_encrypt

    key, nonce, aad = os.urandom(32), os.urandom(12), b"ad"
    for message in (b"", b"x", os.urandom(1000)):
        box = _aead_encrypt(message, aad, nonce, key)
        assert box == bindings.crypto_aead_chacha20poly1305_ietf_encrypt(message, aad, nonce, key)
        assert _aead_decrypt(box, aad, nonce, key) == message
        flipped = bytes([box[0] ^ 1]) + box[1:]
        with pytest.raises(CryptoError):
            _aead_decrypt(flipped, aad, nonce, key)
        with pytest.raises(CryptoError):
            _aead_decrypt(box, b"other", nonce, key)
    for short in (b"", b"x" * 15):  # shorter than a tag: refused as any forged box is
        with pytest.raises(CryptoError):
            _aead_decrypt(short, aad, nonce, key)


# -- the envelope's box: canonical base64 only ------------------------------------------


def _old_canonical(payload: str) -> bool:
    """The plain check the fast one stands in for: decode leniently, re-encode it all, compare."""
    try:
        raw = binascii.a2b_base64(payload)
    except ValueError:
        raw = b""
    return bool(raw) and binascii.b2a_base64(raw, newline=False) == payload.encode()


def _new_canonical(payload: str) -> bool:
    """The check `Session._accept` makes, both ways it is made: each must say the same.

    binascii's (strict decoding, the length, the last quantum), and the one in use (SIMD
    base64 where installed: its decoding, the whole box encoded again and compared).
    """
    std, used = _box_bytes_std(payload), _box_bytes(payload)
    assert std == used, repr(payload)
    return bool(used)


_B64 = string.ascii_letters + string.digits + "+/"


# the alphabet, padding, the url-safe letters, whitespace, and a few that are none of them
_HOSTILE = _B64 + "=-_ \n\r\t.\x00é"


def _spellings(raw: bytes) -> list[str]:
    """The canonical spelling of ``raw`` and near ones: other tail bits, padding, spaces."""
    good = binascii.b2a_base64(raw, newline=False).decode("ascii")
    out = [good, good.rstrip("="), good + "=", good + "==", " " + good, good + "\n"]
    out += [good[:i] + "\n" + good[i:] for i in range(0, len(good), 5)]
    out.append(good.replace("+", "-").replace("/", "_"))
    stripped = good.rstrip("=")
    if stripped:
        # every letter in the last position: the unused bits set in all ways
        out += [stripped[:-1] + c + good[len(stripped) :] for c in _B64]
    return out


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=40))
def test_the_box_check_accepts_what_the_old_one_did_near_a_canonical_spelling(
    raw: bytes,
) -> None:
    for text in _spellings(raw):
        assert _new_canonical(text) == _old_canonical(text), repr(text)


@settings(max_examples=2000, deadline=None)
@given(st.text(alphabet=_HOSTILE, max_size=24))
def test_the_box_check_accepts_what_the_old_one_did_for_any_text(text: str) -> None:
    assert _new_canonical(text) == _old_canonical(text), repr(text)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=3000))
def test_the_box_is_spelled_as_binascii_spells_it(raw: bytes) -> None:
    assert _box_text(raw) == binascii.b2a_base64(raw, newline=False)


@pytest.mark.parametrize(
    "text", ["", "=", "====", "QQ", "QQ=", "QR==", "QQ===", "QQ==QQ==", "QUI=", "QUJD", " QUJD"]
)
def test_the_box_check_on_the_known_edge_cases(text: str) -> None:
    assert _new_canonical(text) == _old_canonical(text)
