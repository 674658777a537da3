"""Directory statements (docs/wire.md): what is signed, and every way a forgery is refused."""

from __future__ import annotations

import base64

import orjson
import pytest

from agents._directory_auth import DirectoryAuth, DirectoryStatementError, make_nonce
from agents._security import KeyPair, TrustStore

FED = "fed"


def _pair() -> tuple[DirectoryAuth, DirectoryAuth, KeyPair]:
    """uav-b's signer and uav-a's checker (both trusted), and an untrusted key."""
    a, b, x = KeyPair.generate("uav-a"), KeyPair.generate("uav-b"), KeyPair.generate("uav-x")
    trust = TrustStore(FED, {"uav-a": a.public_key, "uav-b": b.public_key})
    return DirectoryAuth(FED, b, trust), DirectoryAuth(FED, a, trust), x


def _edit(payload: bytes, **fields: object) -> bytes:
    return orjson.dumps({**orjson.loads(payload), **fields})


def test_a_signed_event_opens_once_and_in_order() -> None:
    signer, checker, _ = _pair()
    first = signer.seal("uav-b", "df-event", {"op": "leave"})
    second = signer.seal("uav-b", "df-event", {"op": "leave"})
    assert checker.open(second, "df-event", platform="uav-b").seq == 2
    with pytest.raises(DirectoryStatementError, match=r"^stale"):
        checker.open(first, "df-event", platform="uav-b")  # older
    with pytest.raises(DirectoryStatementError, match=r"^stale"):
        checker.open(second, "df-event", platform="uav-b")  # replayed


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"body": '{"op":"deregister"}'}, "signature does not verify"),
        ({"seq": 99}, "signature does not verify"),
        ({"boot": 1}, "signature does not verify"),
        ({"ts_ms": 1}, "signature does not verify"),
        ({"from": "uav-a"}, "published under"),
        ({"fed": "other"}, "federation"),
        ({"kind": "df"}, "a 'df' statement"),
        ({"v": 2}, "version"),
        ({"sig": base64.b64encode(bytes(64)).decode()}, "signature does not verify"),
        ({"sig": "not base64!"}, "not base64"),
    ],
)
def test_any_changed_field_is_refused(change: dict[str, object], reason: str) -> None:
    signer, checker, _ = _pair()
    payload = _edit(signer.seal("uav-b", "df-event", {"op": "leave"}), **change)
    with pytest.raises(DirectoryStatementError, match=reason):
        checker.open(payload, "df-event", platform="uav-b")


def test_unsigned_untrusted_and_stale_statements_are_refused() -> None:
    signer, checker, rogue = _pair()
    unsigned = DirectoryAuth(FED, None, None).seal("uav-b", "df-event", {"op": "leave"})
    with pytest.raises(DirectoryStatementError, match="unsigned"):
        checker.open(unsigned, "df-event", platform="uav-b")
    outsider = DirectoryAuth(FED, rogue, None).seal("uav-x", "df-event", {"op": "leave"})
    with pytest.raises(DirectoryStatementError, match="not in the trust file"):
        checker.open(outsider, "df-event", platform="uav-x")
    # uav-x signing in uav-b's name
    impostor = DirectoryAuth(FED, rogue, None).seal("uav-b", "df-event", {"op": "leave"})
    with pytest.raises(DirectoryStatementError, match="signature does not verify"):
        checker.open(impostor, "df-event", platform="uav-b")
    late = DirectoryAuth(FED, signer.keys, None, clock=lambda: 1_000_000.0)
    with pytest.raises(DirectoryStatementError, match="timestamp"):
        checker.open(late.seal("uav-b", "df-event", {}), "df-event", platform="uav-b")
    for junk in (b"junk", b"[]", b'{"v":1}'):
        with pytest.raises(DirectoryStatementError):
            checker.open(junk, "df-event", platform="uav-b")


def test_an_answer_must_sign_the_askers_nonce_and_orders_later_events() -> None:
    signer, checker, _ = _pair()
    signer.seal("uav-b", "df-event", {"op": "leave"})  # seq 1, reflected by the answer
    nonce = make_nonce()
    answer = signer.seal("uav-b", "df", [], nonce=nonce)
    with pytest.raises(DirectoryStatementError, match="nonce differs"):
        checker.open(answer, "df", platform="uav-b", nonce=make_nonce())
    opened = checker.open(answer, "df", platform=None, nonce=nonce)
    assert (opened.platform, opened.seq, opened.body) == ("uav-b", 1, [])
    event = signer.seal("uav-b", "df-event", {"op": "leave"})  # seq 2: newer, accepted
    assert checker.open(event, "df-event", platform="uav-b").seq == 2
    # an answer is never an event (the kind is signed)
    with pytest.raises(DirectoryStatementError):
        checker.open(_edit(answer, kind="df-event"), "df-event", platform="uav-b")
