"""What a member can still make a platform accept, and limits a config gives as ``inf``.

A member that said, signed, that it left is not served until its signed directory
snapshot lists it again. Its membership and directory subscriptions are bounded per
platform, and the checks its requests make a platform ask of a third one are
rate-limited, each refusal counted and audited. A config's numeric limits are checked
when the file is read (a limit of ``inf`` or ``nan`` is TOML, and none of ours means
anything with it), naming file, table and key.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from test_member_authz import (
    WAIT,
    World,
    audited,
    audited_in_file,
    in_file,
    mallory,
    refusal,
    until,
    world,
)

from agents import FIPA_AGENT_MANAGEMENT, Refused, request
from agents._df import MAX_DF_SUBSCRIPTIONS
from agents._platform import REFUSAL_AUDIT_INTERVAL, REFUSALS_ONE_BY_ONE
from agents._protocols import SubscriptionStream, subscribe
from federation import PlatformConfig, PlatformConfigError
from federation._service import ACCEPT_BURST, ACCEPT_RATE, MAX_MEMBERSHIP_SUBSCRIPTIONS

_BASE = 'name = "uav-a"\nfederation = "f"\nkey = "k"\ntrust = "t"\nvocabulary = {}\nmapping = {}\n'


@pytest.mark.parametrize(
    ("table", "key", "value"),
    [
        ("rate_limit", "rate", "inf"),
        ("rate_limit", "total_burst", "nan"),
        ("kx_limit", "per_peer", "inf"),
        ("kx_limit", "report_interval", "inf"),
        ("df_event_limit", "total", "+inf"),
        ("df_event_limit", "per_platform", "-1.0"),
        ("console", "idle_timeout", "nan"),
        ("transport", "serve_timeout", "inf"),
    ],
)
def test_a_limit_of_inf_nan_or_below_zero_is_refused_when_the_file_is_read(
    tmp_path: Path, table: str, key: str, value: str
) -> None:
    path = tmp_path / "uav-a.toml"
    path.write_text(f"{_BASE}[{table}]\n{key} = {value}\n")
    with pytest.raises(PlatformConfigError, match=rf"^{path}: {table}\.{key}: ") as caught:
        PlatformConfig.load(path)
    assert value.lstrip("+-") in ("inf", "nan") or "greater than" in caught.value.message
    path.write_text(f"{_BASE}export_lease = inf\n")
    with pytest.raises(PlatformConfigError, match=rf"^{path}: export_lease: .*finite"):
        PlatformConfig.load(path)


def test_the_node_refuses_an_inf_limit_naming_file_table_and_key(tmp_path: Path) -> None:
    """``dyknow node`` (a process): exit 2 and one line naming where, not a start-up error."""
    path = tmp_path / "uav-a.toml"
    path.write_text(f"{_BASE}[rate_limit]\nrate = inf\n")
    run = subprocess.run(
        [sys.executable, "-m", "federation.cli", "node", "--config", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 2, run.stderr
    assert f"{path}: rate_limit.rate: Input should be a finite number" in run.stderr
    assert "Traceback" not in run.stderr


@pytest.mark.timeout(180)  # as its siblings: its world's own bound is 150 s
async def test_a_member_that_said_it_left_is_not_served_until_listed_again(
    tmp_path: Path,
) -> None:
    """uav-m says, signed, that it leaves, and keeps asking uav-a (a spawned platform)."""
    async with asyncio.timeout(150), world(tmp_path, ["uav-a"]) as w:
        m = w.here["uav-m"]
        fed = m.federation_agent
        assert (await fed.create_stream("uav-a", ["car0-state"], timeout=WAIT)).startswith("x-")
        assert m.agents.df is not None
        await m.agents.df.announce_leave()
        # uav-a took it for gone (its exports to it stopped); before, it went on serving it
        await w.until_stats("uav-a", lambda s: s["exports"] == [], "uav-m taken for gone")
        with pytest.raises(Refused, match=r"refused: left: 'uav-m' said, signed, that it left"):
            await fed.create_stream("uav-a", ["car1-state"], timeout=WAIT)
        s = await w.stats("uav-a")
        assert s["platform"]["from_left"] == 1 and s["exports"] == []
        recs = audited(s, verdict="refused", sender="federation@uav-m", reason="left: 'uav-m'")
        assert len(recs) == 1, recs
        # it announces itself again (as a new process would): its presence comes back and
        # its directory answers, signed; listed again, it is served again
        agents = m.agents
        agents.df._left = False
        assert agents._token is not None
        await agents._token.aclose()
        await asyncio.sleep(0.5)
        agents._token = await agents.transport.declare_token(agents.key("alive"))
        async with asyncio.timeout(WAIT):
            while True:
                try:
                    await fed.create_stream("uav-a", ["car1-state"], timeout=WAIT)
                    break
                except Refused as exc:
                    assert "left: 'uav-m'" in str(exc)
                    await asyncio.sleep(0.2)


FEDERATION_ONTOLOGY = "dyknow-federation"


@pytest.mark.timeout(180)
async def test_membership_subscriptions_are_bounded_per_platform(tmp_path: Path) -> None:
    # Every membership event informs every subscriber: unbounded, one member's thousands
    # of subscriptions cost the victim memory (~3 kB each) and turn each event into a flood.
    async with asyncio.timeout(150), world(tmp_path, ["uav-a"], ["uav-m"]) as w:
        m = await mallory(w)
        ask = {"membership": True}
        held: list[SubscriptionStream] = []
        for _ in range(MAX_MEMBERSHIP_SUBSCRIPTIONS):
            held.append(await subscribe(m, "federation@uav-a", ask, ontology=FEDERATION_ONTOLOGY))
        extra = 5
        for _ in range(extra):
            reason = await refusal(
                subscribe(m, "federation@uav-a", ask, ontology=FEDERATION_ONTOLOGY)
            )
            assert reason == (
                "too many membership subscriptions for uav-m "
                f"(limit {MAX_MEMBERSHIP_SUBSCRIPTIONS}: {MAX_MEMBERSHIP_SUBSCRIPTIONS} held)"
            )
        s = await w.stats("uav-a")
        assert s["membership_subscribers"] == MAX_MEMBERSHIP_SUBSCRIPTIONS
        assert s["refusals"].get("subscription-limit") == extra
        await audited_in_file(
            tmp_path,
            s,
            extra,
            verdict="refused",
            stage="federation",
            code="subscription-limit",
            sender="mallory@uav-m",
            performative="subscribe",
            reason="subscription-limit: too many membership subscriptions for uav-m",
        )
        # a cancelled subscription frees its place
        await held.pop().cancel()
        held.append(await subscribe(m, "federation@uav-a", ask, ontology=FEDERATION_ONTOLOGY))
        with pytest.raises(Refused):
            await subscribe(m, "federation@uav-a", ask, ontology=FEDERATION_ONTOLOGY)
        s = await w.stats("uav-a")
        assert s["membership_subscribers"] == MAX_MEMBERSHIP_SUBSCRIPTIONS
        assert s["refusals"].get("subscription-limit") == extra + 1
        for stream in held:
            await stream.cancel()


@pytest.mark.timeout(180)
async def test_directory_subscriptions_are_bounded_per_platform(tmp_path: Path) -> None:
    # Each directory subscription is kept and told of every change: unbounded, 2,000
    # FIPA-Subscribes from uav-m to df@uav-a were all agreed (~7 MB). Bounded per platform.
    async with asyncio.timeout(150), world(tmp_path, ["uav-a"], ["uav-m"]) as w:
        m = await mallory(w)
        held: list[SubscriptionStream] = []
        for _ in range(MAX_DF_SUBSCRIPTIONS):
            held.append(await subscribe(m, "df@uav-a", {}, ontology=FIPA_AGENT_MANAGEMENT))
        # the member repeats them at once: each refused and counted; audited one by one
        # within its budget, the rest summed up (a record each would flood the audit)
        extra = 40
        told = (
            "too many directory subscriptions for uav-m "
            f"(limit {MAX_DF_SUBSCRIPTIONS}: {MAX_DF_SUBSCRIPTIONS} held)"
        )
        t0 = time.monotonic()
        reasons = await asyncio.gather(
            *[
                refusal(subscribe(m, "df@uav-a", {}, ontology=FIPA_AGENT_MANAGEMENT))
                for _ in range(extra)
            ]
        )
        elapsed = time.monotonic() - t0
        assert reasons == [f"subscription-limit: {told}"] * extra
        s = await _audited_within_budget(
            w,
            tmp_path,
            elapsed,
            "subscription-limit",
            extra,
            told,
            stage="df",
            performative="subscribe",
        )
        assert s["df_subscribers"] == MAX_DF_SUBSCRIPTIONS
        assert s["df_subscriptions_refused"] == extra
        await held.pop().cancel()  # a cancelled subscription frees its place
        held.append(await subscribe(m, "df@uav-a", {}, ontology=FIPA_AGENT_MANAGEMENT))
        for stream in held:
            await stream.cancel()


@pytest.mark.timeout(180)
async def test_a_member_cannot_make_a_platform_ask_a_third_one_at_will(tmp_path: Path) -> None:
    # accept-stream names a requester; the receiver checks with it (confirm-stream). Each
    # such check is a request of the victim's to the requester: unbounded, 500
    # accept-streams from uav-m made uav-a send 409 confirm-streams (64 labels each) to the
    # operator, whose audit then showed uav-a asking. Bounded per provider, refused past it.
    consent = {"sharing": {"accept_for": ["operator"]}}
    async with (
        asyncio.timeout(150),
        world(tmp_path, ["uav-a"], ["operator", "uav-m"], uav_a=consent) as w,
    ):
        m = await mallory(w)
        operator = w.here["operator"].federation_agent
        content = {
            "action": "accept-stream",
            "requester": "operator",
            "labels": [f"car{i}-state" for i in range(64)],
        }
        n, at_once = 100, 10
        t0 = time.monotonic()
        reasons: list[str] = []
        # ten at a time: a hundred (~140 kB) in one turn overran zenoh's send queue on a
        # busy machine, which drops what does not fit (congestion control DROP), and the
        # requests it dropped were never answered
        for _ in range(n // at_once):
            reasons += await asyncio.gather(
                *[
                    refusal(request(m, "federation@uav-a", content, ontology=FEDERATION_ONTOLOGY))
                    for _ in range(at_once)
                ]
            )
        elapsed = time.monotonic() - t0
        checked = [r for r in reasons if "did not confirm" in r]
        limited = [r for r in reasons if r.startswith("too many accept-stream requests")]
        assert len(checked) + len(limited) == n, reasons
        allowed = ACCEPT_BURST + ACCEPT_RATE * elapsed + 1
        assert 1 <= len(checked) <= allowed, (len(checked), elapsed)
        assert limited[0] == (
            f"too many accept-stream requests from uav-m (at most {ACCEPT_RATE:g}/s, bursts "
            f"of {ACCEPT_BURST:g}): not checked with operator"
        )
        # the operator was asked only for those checked
        assert operator.refusals.get("consent") == len(checked)
        s = await _audited_within_budget(
            w, tmp_path, elapsed, "consent-rate", len(limited), limited[0]
        )
        assert s["refusals"].get("consent-rate") == len(limited)


@pytest.mark.timeout(180)
async def test_a_member_cannot_make_a_provider_ask_third_platforms_at_will(
    tmp_path: Path,
) -> None:
    # create-stream with to-units naming uav-b makes the provider ask uav-b
    # (accept-stream) before anything else: unbounded, a member repeating it made uav-a
    # send uav-b as many requests, refused there in uav-a's name. Bounded per requester.
    async with asyncio.timeout(150), world(tmp_path, ["uav-a"], ["uav-b", "uav-m"]) as w:
        m = await mallory(w)
        receiver = w.here["uav-b"].federation_agent
        content = {"action": "create-stream", "labels": ["car1-state"], "to-units": ["uav-b"]}
        n = 60
        t0 = time.monotonic()
        reasons = await asyncio.gather(
            *[
                refusal(request(m, "federation@uav-a", content, ontology=FEDERATION_ONTOLOGY))
                for _ in range(n)
            ]
        )
        elapsed = time.monotonic() - t0
        asked = [r for r in reasons if r.startswith("receiver uav-b did not agree")]
        limited = [r for r in reasons if r.startswith("too many create-streams")]
        assert len(asked) + len(limited) == n, reasons
        assert 1 <= len(asked) <= ACCEPT_BURST + ACCEPT_RATE * elapsed + 1, (asked, elapsed)
        assert limited[0] == (
            f"too many create-streams for other platforms from uav-m (at most "
            f"{ACCEPT_RATE:g}/s, bursts of {ACCEPT_BURST:g}): uav-b not asked"
        )
        # uav-b was asked only for those
        assert receiver.refusals.get("consent") == len(asked)
        s = await _audited_within_budget(
            w, tmp_path, elapsed, "consent-rate", len(limited), limited[0]
        )
        assert s["refusals"].get("consent-rate") == len(limited)
        assert not s["agreed"]  # nothing was exported


async def _audited_within_budget(
    w: World,
    tmp_path: Path,
    elapsed: float,
    code: str,
    total: int,
    told: str,
    *,
    stage: str = "federation",
    performative: str = "request",
) -> dict[str, Any]:
    """uav-a's stats once each of uav-m's ``total`` refusals of ``code`` (``told``: the
    reason, the same each time) is audited: within the member's budget one by one (the
    whole reason), the rest summed up per interval (``count``, the last reason); none
    lost, and the audit a few records a second however many refusals, not one each."""

    def mine(s: dict[str, Any]) -> list[dict[str, Any]]:
        return [r for r in s["audit"] if r["from"] == "uav-m" and r.get("stage") == stage]

    def of_code(s: dict[str, Any]) -> list[dict[str, Any]]:
        return [r for r in mine(s) if r["code"] == code]

    # what is summed up is written at the interval's end: until every refusal is
    s = await w.until_stats(
        "uav-a",
        lambda s: sum(r.get("count") or 1 for r in of_code(s)) == total,
        f"every {code} refusal audited, one by one or summed up",
    )
    # a budget's worth of uav-m's refusals one by one per interval at most (each interval
    # starts at a refusal), and its first refusals are all within one
    intervals = int(elapsed // REFUSAL_AUDIT_INTERVAL) + 1
    one_by_one = [r for r in mine(s) if r.get("count") is None]
    assert REFUSALS_ONE_BY_ONE <= len(one_by_one) <= REFUSALS_ONE_BY_ONE * intervals, (
        len(one_by_one),
        elapsed,
    )
    recs = of_code(s)
    summed = [r for r in recs if r.get("count") is not None]
    for r in recs:
        assert r["verdict"] == "refused", r
        if r.get("count") is None:
            assert r["sender"] == "mallory@uav-m" and r["performative"] == performative, r
            assert r["reason"] == f"{code}: {told}", r
        else:
            assert r["sender"] is None and r["performative"] is None, r
            assert r["reason"].startswith(
                f"{code}: {r['count']} more request(s) refused without a record each (over "
                f"{REFUSALS_ONE_BY_ONE} per {REFUSAL_AUDIT_INTERVAL:g} s of one platform), "
                "from 'uav-m'"
            ), r
            assert r["reason"].endswith(f" (last: {told})"), r
    if total > REFUSALS_ONE_BY_ONE * intervals:  # more than could each have a record
        assert summed, recs
    # one summary per interval at most (and one at once)
    assert len(summed) <= intervals + 1, (len(summed), elapsed)
    await until(lambda: in_file(tmp_path, "uav-a", recs[-1]), "the record in the audit file")
    return s
