"""Attacks a member could still make after issue 11's first fixes, now refused.

The attacker is a member: ``uav-m`` runs our own library with a key in the federation's
trust file, so everything it sends is authenticated. The victim is a spawned
`FederationPlatform` process (the harness of ``test_member_authz``), asked over a pipe
for its counters and audit records. Each test asserts the refusal, its count and its
audit record.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from test_faults import until
from test_member_authz import audited, in_file, mallory, refusal, world

from agents import Refused
from agents._protocols import SubscriptionStream, subscribe
from federation._service import MAX_MEMBERSHIP_SUBSCRIPTIONS

pytestmark = pytest.mark.timeout(180)

FEDERATION_ONTOLOGY = "dyknow-federation"


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
        recs = audited(
            s,
            verdict="refused",
            stage="federation",
            code="subscription-limit",
            sender="mallory@uav-m",
            performative="subscribe",
            reason="subscription-limit: too many membership subscriptions for uav-m",
        )
        assert len(recs) == extra
        await until(lambda: in_file(tmp_path, "uav-a", recs[-1]), "the record in the audit file")
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
