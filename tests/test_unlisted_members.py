"""A member the global directory does not list yet is said, and listed soon after it answers.

Real platforms over zenoh on loopback, each with its key and the trust file. uav-b's
Directory Facilitator holds its answers back (as a loaded one does: each query ends at
its timeout) while it joins: uav-a took its signed events (it joined) but never
its signed snapshot, so uav-a refuses its presence and drops its entries. A global request
then names uav-b ``unlisted`` instead of leaving it out silently; once uav-b's directory
answers again, uav-a lists it within a few seconds (before: at the next recheck, 30 s).
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from agents import DirectoryFacilitator
from agents._df import UNCONFIRMED_MAX_WAIT
from agents.keys import gen_keys, trust_keys
from agents.transports import free_tcp_port
from federation import FederationPlatform, PlatformConfig

WAIT = 15.0
pytestmark = pytest.mark.timeout(120)


def _federation(tmp: Path, fed: str) -> None:
    """uav-a listening, uav-b connecting to it; both trusted."""
    names = ["uav-a", "uav-b"]
    port = free_tcp_port()
    transport = {
        "uav-a": f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]',
        "uav-b": f'mode = "peer"\nconnect = ["tcp/127.0.0.1:{port}"]',
    }
    pubs = [gen_keys(n, tmp / "keys")[2] for n in names]
    trust_keys(tmp / "trust.json", pubs, federation=fed)
    (tmp / "vocab.toml").write_text(f'name = "{fed}"\n[labels]\n"heli-altitude" = "m"\n')
    for n in names:
        (tmp / f"{n}-labels.toml").write_text(
            f'vocabulary = "{fed}"\n[labels]\n"heli-altitude" = "{n}/alt"\n'
        )
        (tmp / f"{n}.toml").write_text(
            f'name = "{n}"\nfederation = "{fed}"\nkey = "keys/{n}.key"\ntrust = "trust.json"\n'
            f'vocabulary = "vocab.toml"\nmapping = "{n}-labels.toml"\n'
            f'audit = "{n}-audit.jsonl"\n\n[transport]\n{transport[n]}\n'
        )


class _Withheld:
    """uav-b's directory holds every query unanswered while ``on`` (counted), as a slow one."""

    def __init__(self) -> None:
        self.on = True
        self.held = 0
        self._released: asyncio.Event | None = None

    def release(self) -> None:
        self.on = False
        if self._released is not None:
            self._released.set()  # those held answer now: within their timeout, they count

    def serve(self, real: Callable[..., Awaitable[bytes | None]]) -> Callable[..., Any]:
        async def serve(df: DirectoryFacilitator, key: str, payload: bytes) -> bytes | None:
            if self.on and df.platform.name == "uav-b":
                self.held += 1
                if self._released is None:
                    self._released = asyncio.Event()
                try:
                    async with asyncio.timeout(WAIT):
                        await self._released.wait()
                except TimeoutError:
                    return None
            return await real(df, key, payload)

        return serve


@pytest.fixture
def withheld(monkeypatch: pytest.MonkeyPatch) -> Iterator[_Withheld]:
    w = _Withheld()
    monkeypatch.setattr(
        DirectoryFacilitator, "_serve_public", w.serve(DirectoryFacilitator._serve_public)
    )
    yield w


async def _until(what: str, check: Callable[[], Any], wait: float = WAIT) -> Any:
    deadline = time.monotonic() + wait
    while not (value := check()):
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {wait} s: {what}")
        await asyncio.sleep(0.05)
    return value


def _presence_refusals(a: FederationPlatform) -> list[dict[str, Any]]:
    return [
        r
        for r in a.interface.audit.records
        if r.get("stage") == "presence" and r.get("from") == "uav-b"
    ]


async def _joined_unconfirmed(a: FederationPlatform, b: FederationPlatform) -> None:
    """uav-b joins while uav-a asks for its snapshot, which never comes: refused, a member."""
    gdf = a.agents.global_df
    assert gdf is not None
    # uav-a asks uav-b's snapshot (three query timeouts) from its presence on: the signed
    # events of uav-b's joining meanwhile are taken
    await _until("uav-a asks for uav-b's snapshot", lambda: "uav-b" in gdf.platforms)
    await b.join()
    await _until("uav-a takes uav-b's joining", lambda: "uav-b" in a.members)
    await _until("uav-a refuses uav-b's presence", lambda: "uav-b" in gdf.unconfirmed)
    assert "uav-b" not in gdf.platforms and not gdf.services("uav-b")


async def test_a_member_not_listed_yet_is_unlisted_then_listed_once_it_answers(
    tmp_path: Path, withheld: _Withheld
) -> None:
    fed = f"unlisted{os.getpid()}a"
    _federation(tmp_path, fed)
    async with (
        asyncio.timeout(6 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-b.toml"), join=False) as b,
    ):
        gdf = a.agents.global_df
        assert gdf is not None
        refused = gdf.refused
        await _joined_unconfirmed(a, b)
        assert gdf.refused == refused + 1
        records = _presence_refusals(a)
        assert len(records) == 1, records
        assert "presence without a signed directory answer" in records[0]["reason"]

        fed_a = a.federation_agent
        result = await fed_a.global_request({"action": "list-labels"}, deadline=2.0)
        assert result.asked == [] and result.answers == {} and result.no_answer == []
        assert result.unlisted == ["uav-b"]
        assert result.to_content()["unlisted"] == ["uav-b"]
        with_self = await fed_a.global_request(
            {"action": "list-labels"}, deadline=2.0, include_self=True
        )
        assert with_self.asked == ["uav-a"] and with_self.unlisted == ["uav-b"]

        # asked again while its presence holds, with a wait that grows: no storm of queries
        before, since = withheld.held, time.monotonic()
        await asyncio.sleep(3 * UNCONFIRMED_MAX_WAIT)  # what is measured is the query count
        held = time.monotonic() - since
        asked = withheld.held - before
        print(f"uav-b asked {asked} times in {held:.1f} s while its directory was withheld")
        assert 1 <= asked <= held / 1.0 + 1, asked
        assert gdf.refused == refused + 1 and len(_presence_refusals(a)) == 1  # refused once

        withheld.release()
        answers = time.monotonic()
        await _until(
            "uav-a lists uav-b once it answers",
            lambda: "uav-b" in fed_a.providers(),
            wait=2 * UNCONFIRMED_MAX_WAIT + 4.0,
        )
        took = time.monotonic() - answers
        print(f"uav-b listed {took:.2f} s after its directory answered again")
        assert gdf.unconfirmed == [] and "uav-b" in gdf.platforms
        result = await fed_a.global_request({"action": "list-labels"}, deadline=WAIT)
        assert result.asked == ["uav-b"] and list(result.answers) == ["uav-b"]
        assert result.unlisted == []


async def test_an_unlisted_member_that_goes_is_gone(tmp_path: Path, withheld: _Withheld) -> None:
    """Its presence ends before its snapshot ever came: members told ``gone``, not kept."""
    fed = f"unlisted{os.getpid()}b"
    _federation(tmp_path, fed)
    async with (
        asyncio.timeout(6 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
    ):
        gdf = a.agents.global_df
        assert gdf is not None
        async with a.membership() as events:
            async with FederationPlatform(
                PlatformConfig.load(tmp_path / "uav-b.toml"), join=False
            ) as b:
                await _joined_unconfirmed(a, b)
            await _until("uav-a's members without uav-b", lambda: "uav-b" not in a.members)
            assert gdf.unconfirmed == []
            kinds = [e.kind for e in events.inbox.drain() if e.platform == "uav-b"]
            assert kinds == ["joined", "gone"], kinds
        result = await a.federation_agent.global_request({"action": "list-labels"}, deadline=2.0)
        assert result.unlisted == []
