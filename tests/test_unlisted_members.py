"""A member the global directory does not list yet is said, and listed soon after it answers.

Real platforms over zenoh on loopback, each with its key and the trust file. uav-b's
Directory Facilitator holds its answers back (as a loaded one does: each query ends at
its timeout) while it joins: uav-a took its signed events (it joined) but never
its signed snapshot, so uav-a refuses its presence and drops its entries. A global request
then names uav-b ``unlisted`` instead of leaving it out silently; once uav-b's directory
answers again, uav-a lists it within a few seconds (before: at the next recheck, 30 s);
what it deregistered meanwhile is told then. An outsider's plain zenoh peer holds a token
under a trusted name (asked again at a bounded rate), or holds the recheck's query open
while a member leaves (its answer to it must not serve it again).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from agents import Agent, DirectoryFacilitator, request, wire_key
from agents import _df as df_module
from agents._df import UNCONFIRMED_MAX_WAIT, GlobalDirectory
from agents.keys import gen_keys, trust_keys
from agents.transports import free_tcp_port
from federation import FederationPlatform, PlatformConfig
from federation._service import ONTOLOGY

WAIT = 15.0
pytestmark = pytest.mark.timeout(120)


def _federation(tmp: Path, fed: str) -> int:
    """uav-a listening, uav-b connecting to it; both trusted. The port uav-a listens on."""
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
    return port


@contextlib.contextmanager
def _outsider(port: int) -> Iterator[zenoh.Session]:
    """A plain zenoh peer of an outsider (no key of the federation), on loopback."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    session = zenoh.open(cfg)
    try:
        yield session
    finally:
        session.close()


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
def asked(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """When uav-a's directory view asked uav-b alone (monotonic), from now on."""
    times: list[float] = []
    real = GlobalDirectory._query

    async def counted(
        self: GlobalDirectory, platform: str, *args: Any, **kwargs: Any
    ) -> dict[str, Any]:
        if platform == "uav-b" and self._platform.name == "uav-a":
            times.append(time.monotonic())
        return await real(self, platform, *args, **kwargs)

    monkeypatch.setattr(GlobalDirectory, "_query", counted)
    return times


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
    tmp_path: Path, withheld: _Withheld, asked: list[float]
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
        # two rechecks unanswered (30-60 s: a loaded machine) would take uav-b for gone:
        # its own asking again is what is tested here
        gdf.recheck_interval = None
        refused = gdf.refused
        await _joined_unconfirmed(a, b)
        refused_at = time.monotonic()
        assert gdf.refused == refused + 1
        records = _presence_refusals(a)
        assert len(records) == 1, records
        assert "presence without a signed directory answer" in records[0]["reason"]

        fed_a = a.federation_agent
        result = await fed_a.global_request({"action": "list-labels"}, deadline=2.0)
        assert result.asked == [] and result.answers == {} and result.no_answer == []
        assert result.unlisted == ["uav-b"]
        # what a local agent asking over ACL (and the console) is told
        asker = await a.agents.add(Agent("asker"))
        content = {"action": "global-request", "request": {"action": "list-labels"}, "deadline": 1}
        told = await request(asker, "federation@uav-a", content, ontology=ONTOLOGY)
        assert isinstance(told, dict) and told["unlisted"] == ["uav-b"], told
        assert told["asked"] == [] and told["no-answer"] == []
        with_self = await fed_a.global_request(
            {"action": "list-labels"}, deadline=2.0, include_self=True
        )
        assert with_self.asked == ["uav-a"] and with_self.unlisted == ["uav-b"]

        # asked again while its presence holds, the wait doubling up to its bound: three
        # askings after the refusal (one would come every 2 s without the backoff)
        first = len(asked)
        await _until("uav-b asked again thrice", lambda: len(asked) >= first + 3, 4 * WAIT)
        asks = asked[first:]
        gaps = [round(b - a, 2) for a, b in itertools.pairwise(asks)]
        held = asks[-1] - refused_at
        print(f"uav-b asked {len(asks)} times in {held:.1f} s after its refusal; gaps {gaps}")
        assert len(asks) <= held / UNCONFIRMED_MAX_WAIT + 3, asks
        assert max(gaps) >= UNCONFIRMED_MAX_WAIT, gaps
        assert gdf.refused == refused + 1 and len(_presence_refusals(a)) == 1  # refused once
        assert "uav-b" not in gdf.platforms  # asked, not listed, meanwhile

        withheld.release()
        answers = time.monotonic()
        await _until("uav-a lists uav-b once it answers", lambda: "uav-b" in fed_a.providers())
        took = time.monotonic() - answers
        print(f"uav-b listed {took:.2f} s after its directory answered again")
        # the query held meanwhile is answered at once: listed within its answer's time
        assert took < 3.0, took
        assert gdf.unconfirmed == [] and "uav-b" in gdf.platforms
        result = await fed_a.global_request({"action": "list-labels"}, deadline=WAIT)
        assert result.asked == ["uav-b"] and list(result.answers) == ["uav-b"]
        assert result.unlisted == []


async def test_a_service_deregistered_while_unlisted_is_told_once_listed(
    tmp_path: Path, withheld: _Withheld
) -> None:
    """uav-b leaves the federation (signed) while not listed: members told once it answers."""
    fed = f"unlisted{os.getpid()}c"
    _federation(tmp_path, fed)
    async with (
        asyncio.timeout(6 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-b.toml"), join=False) as b,
    ):
        gdf = a.agents.global_df
        assert gdf is not None
        async with a.membership() as events:
            await _joined_unconfirmed(a, b)
            await b.leave()  # its signed deregistrations come while it is not listed
            assert not b.federation_agent.joined
            withheld.release()
            await _until("uav-a lists uav-b", lambda: "uav-b" in gdf.platforms)
            await _until("uav-a's members without uav-b", lambda: "uav-b" not in a.members)
            kinds = [e.kind for e in events.inbox.drain() if e.platform == "uav-b"]
            assert kinds == ["joined", "left"], kinds
        assert gdf.unconfirmed == [] and gdf.services("uav-b") == []
        result = await a.federation_agent.global_request({"action": "list-labels"}, deadline=2.0)
        assert result.asked == [] and result.unlisted == []


async def test_an_unlisted_member_that_goes_is_gone(
    tmp_path: Path, withheld: _Withheld, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Its presence ends before its snapshot ever came: members told ``gone``, not kept."""
    # not asked again meanwhile: the presence ending is what takes it, not a query's end
    monkeypatch.setattr(df_module, "UNCONFIRMED_FIRST_WAIT", 10 * WAIT)
    again: list[str] = []  # uav-a's re-askings of an unconfirmed platform
    real = GlobalDirectory._confirm

    async def confirm(self: GlobalDirectory, platform: str, timeout: float) -> None:
        if self._platform.name == "uav-a":
            again.append(platform)
        await real(self, platform, timeout)

    monkeypatch.setattr(GlobalDirectory, "_confirm", confirm)
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
            # never asked again: the presence's end took it (uav-b's signed leave at its
            # close may still be checked by querying it, as any doubted leave is)
            assert again == [], again
            assert gdf.unconfirmed == []
            kinds = [e.kind for e in events.inbox.drain() if e.platform == "uav-b"]
            assert kinds == ["joined", "gone"], kinds
        result = await a.federation_agent.global_request({"action": "list-labels"}, deadline=2.0)
        assert result.unlisted == []


async def test_a_forged_token_held_is_asked_again_at_a_bounded_rate(
    tmp_path: Path, asked: list[float]
) -> None:
    """An outsider holds a token under trusted uav-b's name (uav-b does not run) and answers
    its directory queries with junk: refused once, asked again with the wait doubling, never
    listed; the junk answers to the re-asking audited summed up, not one record each, even
    when each re-asking is answered 50 more times, each under a name of its own, long."""
    fed = f"unlisted{os.getpid()}d"
    port = _federation(tmp_path, fed)
    async with (
        asyncio.timeout(6 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
    ):
        gdf = a.agents.global_df
        assert gdf is not None
        # two rechecks unanswered (30-60 s: a loaded machine) would take the forged uav-b
        # for gone, and end its asking again: that asking's rate is what is tested here
        gdf.recheck_interval = None
        audit = a.interface.audit
        refused = gdf.refused
        seen: list[list[str]] = []
        invented = itertools.count()
        inventing = False  # once refused: the re-askings are answered under invented names too
        with _outsider(port) as session:

            def junk(query: zenoh.Query) -> None:
                key = str(query.key_expr)
                query.reply(key, b'{"platform": "uav-b", "junk": [')
                for _ in range(50 if inventing else 0):
                    name = f"inv{next(invented)}-" + "y" * 2000
                    query.reply(key, json.dumps({"from": name}).encode())

            queryable = session.declare_queryable(wire_key(fed, "df", "uav-b"), junk)
            token = session.liveliness().declare_token(wire_key(fed, "alive", "uav-b"))
            await _until("uav-a refuses the forged presence", lambda: gdf.unconfirmed)
            inventing = True
            refused_at = time.monotonic()
            first = len(asked)
            while len(asked) < first + 4:  # four askings again, each awaited
                n = len(asked)
                await _until("uav-b asked again", lambda n=n: len(asked) > n, 4 * WAIT)
                seen.append(gdf.platforms)
            token.undeclare()
            await _until("the forged presence's end taken", lambda: not gdf.unconfirmed)
            # an asking counts from when it is sent: its answers (one junk, 50 invented) may
            # still be on the way, on a busy machine not yet at the queryable; each taken
            # and refused before the queryable goes (no asking comes after the presence)
            await _until(
                "every asking's answers refused",
                lambda: gdf.refused >= refused + 3 + 1 + 51 * len(asked[first:]),
            )
            queryable.undeclare()
        again = asked[first:]
        gaps = [round(b - a, 2) for a, b in itertools.pairwise(again)]
        held = again[-1] - refused_at
        print(f"the forged uav-b asked {len(again)} times in {held:.1f} s; gaps {gaps}")
        assert len(again) <= held / UNCONFIRMED_MAX_WAIT + 3, again
        # the wait doubles (1, 2, 4 s), then stays: one asking per 4 s (2 s without backoff)
        assert all(b >= a - 0.5 for a, b in itertools.pairwise(gaps)), gaps
        assert gaps[-1] >= UNCONFIRMED_MAX_WAIT - 0.5, gaps
        assert all("uav-b" not in p for p in seen), seen  # never in the view's platforms
        mine = [r for r in audit.records if r.get("from") == "uav-b"]
        assert [r["stage"] for r in mine if r["stage"] == "presence"] == ["presence"], mine
        summed = [r for r in mine if r["stage"] == "df" and "asked again" in r["reason"]]
        # the first at once (with those taken before it runs), the rest within the
        # interval in the next summary, whatever name each answer claims
        assert len(summed) == 1 and 1 <= summed[0]["count"] <= 51, summed
        # its first three askings answered junk too, each refused as any answer is
        assert len([r for r in mine if r["stage"] == "df"]) == 1 + 3, mine
    summed = [
        r
        for r in audit.records
        if r.get("from") == "uav-b" and r.get("stage") == "df" and "asked again" in r["reason"]
    ]
    assert len(summed) == 2 and sum(r["count"] for r in summed) == 51 * len(again), summed
    # the invented names: cut short in the detail, never a record's key of their own
    assert "'inv" in summed[-1]["reason"], summed
    longest = max(len(str(v)) for r in audit.records for v in r.values())
    assert longest < 1000, longest
    assert not [r for r in audit.records if str(r.get("from", "")).startswith("inv")]
    # each refused answer counted: the first three askings', the presence, the re-askings'
    assert gdf.refused == refused + 3 + 1 + 51 * len(again), (gdf.refused, refused, len(again))


async def test_a_recheck_held_open_does_not_list_a_member_that_left_meanwhile(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An outsider's silent queryable on ``df/zzz`` holds each recheck's query open; uav-b
    answers one, then leaves (signed): the held query's end must not serve it again."""
    answered: list[float] = []  # when uav-b's directory answered a query of every directory
    real = DirectoryFacilitator._serve_public

    async def serve(df: DirectoryFacilitator, key: str, payload: bytes) -> bytes | None:
        out = await real(df, key, payload)
        if df.platform.name == "uav-b" and out is not None and key.endswith("/*"):
            answered.append(time.monotonic())
        return out

    monkeypatch.setattr(DirectoryFacilitator, "_serve_public", serve)
    fed = f"unlisted{os.getpid()}e"
    port = _federation(tmp_path, fed)
    async with (
        asyncio.timeout(6 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
    ):
        gdf = a.agents.global_df
        df = a.agents.df
        assert gdf is not None and df is not None
        with _outsider(port) as session:
            held: list[float] = []  # when each query reached it (kept: a dropped one ends)
            queries: list[zenoh.Query] = []

            def silent(query: zenoh.Query) -> None:
                held.append(time.monotonic())
                queries.append(query)

            queryable = session.declare_queryable(wire_key(fed, "df", "zzz"), silent)
            async with FederationPlatform(PlatformConfig.load(tmp_path / "uav-b.toml")) as b:
                b_df = b.agents.df
                assert b_df is not None
                await _until("uav-a lists uav-b", lambda: "uav-b" in gdf.platforms)
                n = len(held)
                # the recheck asks at once (its interval is due): not before this
                began = time.monotonic()
                gdf.recheck_interval = 1.0
                await _until("a recheck asks every directory", lambda: len(held) > n)
                await _until("uav-b answers it", lambda: answered and answered[-1] >= began)
                # uav-b says, signed, that it leaves (and answers no more), the query held open
                await b_df.announce_leave()
                await _until("uav-b taken for gone", lambda: "uav-b" not in gdf.platforms)
                left = time.monotonic()
                assert left < began + 5.0, f"uav-b left {left - began:.2f} s in: nothing tested"
                assert df.said_left("uav-b")
                n = len(held)
                await _until("the next recheck begins", lambda: len(held) > n)
                print(f"uav-b left {left - began:.2f} s into a recheck held open")
                assert "uav-b" not in gdf.platforms and df.said_left("uav-b")
                assert not gdf.services("uav-b")
            queryable.undeclare()
            queries.clear()


async def test_a_member_listed_on_its_re_asking_is_not_gone_on_one_more_silence(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """uav-b, held unconfirmed, misses one recheck; then it answers uav-a's re-asking of it
    (listed) while its answers to the rechecks' queries of every directory are lost, as a
    loaded one's. Its signed answer since is an answer: taken for gone only once two
    rechecks that began after it found no answer (before: on the next recheck's end)."""
    star_only = False  # uav-b: every query held unanswered; then only those of every directory
    released = asyncio.Event()
    real_serve = DirectoryFacilitator._serve_public

    async def serve(df: DirectoryFacilitator, key: str, payload: bytes) -> bytes | None:
        if df.platform.name == "uav-b" and (key.endswith("/*") or not star_only):
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(WAIT):
                    await (asyncio.Event() if key.endswith("/*") else released).wait()
            if key.endswith("/*"):
                return None
        return await real_serve(df, key, payload)

    rechecks: list[tuple[float, float]] = []  # uav-a's queries of every directory: began, ended
    real_query = GlobalDirectory._query

    async def query(
        self: GlobalDirectory, platform: str, *args: Any, **kwargs: Any
    ) -> dict[str, Any]:
        began = time.monotonic()
        try:
            return await real_query(self, platform, *args, **kwargs)
        finally:
            if platform == "*" and self._platform.name == "uav-a":
                rechecks.append((began, time.monotonic()))

    monkeypatch.setattr(DirectoryFacilitator, "_serve_public", serve)
    monkeypatch.setattr(GlobalDirectory, "_query", query)
    fed = f"unlisted{os.getpid()}f"
    _federation(tmp_path, fed)
    async with (
        asyncio.timeout(6 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-b.toml"), join=False) as b,
    ):
        gdf = a.agents.global_df
        assert gdf is not None
        gdf.recheck_interval = 1.0  # each recheck takes its query's 5 s (8 s, below)
        refused = gdf.refused
        await _joined_unconfirmed(a, b)
        unconfirmed = time.monotonic()
        gdf.query_timeout = 8.0  # the rechecks from now on: uav-b listed well within one
        await _until(
            "a recheck ends with uav-b unconfirmed",
            lambda: rechecks and rechecks[-1][1] > unconfirmed,
            2 * WAIT,
        )
        assert "uav-b" in gdf.unconfirmed, "uav-b taken for gone already: nothing tested"
        star_only = True
        released.set()  # its re-asking answered (the one held now, or the next, within 4 s)
        await _until("uav-a lists uav-b", lambda: "uav-b" in gdf.platforms)
        listed = time.monotonic()
        gdf.query_timeout = 1.0  # rechecks of 5 s again
        await _until("uav-b taken for gone", lambda: "uav-b" not in gdf.platforms, 4 * WAIT)
        gone = time.monotonic()
        after = [r for r in rechecks if listed < r[0] and r[1] <= gone]
        print(
            f"uav-b listed {listed - unconfirmed:.1f} s after unconfirmed, gone after "
            f"{len(after)} recheck(s) begun since ({gone - listed:.1f} s)"
        )
        assert len(after) >= 2, (listed, gone, rechecks)
        # its presence refused, then its silence: each counted and audited once
        assert gdf.refused == refused + 2
        reasons = [r["reason"] for r in _presence_refusals(a)]
        assert len(reasons) == 2, reasons
        assert "answered no signed directory query twice" in reasons[1]
        assert "never listed" not in reasons[1]  # it was listed


async def test_a_forged_name_taken_for_gone_while_asked_again_is_told_no_gone(
    tmp_path: Path,
) -> None:
    """An outsider holds a token under trusted uav-b's name (uav-b never ran) and holds
    uav-a's re-asking of it open; the rechecks take it for gone meanwhile. It was never
    a member, nor were watchers told of any entry of its: no ``gone`` is told (before:
    membership subscribers heard ``gone`` of a platform that never joined)."""
    fed = f"unlisted{os.getpid()}g"
    port = _federation(tmp_path, fed)
    async with (
        asyncio.timeout(6 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
    ):
        gdf = a.agents.global_df
        assert gdf is not None
        gdf.recheck_interval = None
        gdf.query_timeout = 0.5  # its first snapshot's three queries: 1.5 s
        refused = gdf.refused
        directory = gdf.watch()
        async with a.membership() as events:
            with _outsider(port) as session:
                held: list[zenoh.Query] = []

                def hold(query: zenoh.Query) -> None:
                    if not str(query.key_expr).endswith("/*"):
                        held.append(query)  # kept: the asking waits out its timeout

                queryable = session.declare_queryable(wire_key(fed, "df", "uav-b"), hold)
                token = session.liveliness().declare_token(wire_key(fed, "alive", "uav-b"))
                await _until("uav-a refuses the forged presence", lambda: gdf.unconfirmed)
                gdf.query_timeout = 6 * WAIT  # its re-asking held open from now on
                await _until(
                    "uav-b asked again", lambda: "uav-b" in gdf.unconfirmed and gdf._joining
                )
                gdf.recheck_interval = 0.5
                await _until("uav-b taken for gone", lambda: not gdf.unconfirmed)
                assert gdf.refused == refused + 2
                token.undeclare()
                queryable.undeclare()
                held.clear()
        kinds = [e.kind for e in events.inbox.drain() if e.platform == "uav-b"]
        assert kinds == [], kinds
        told = [e.op for e in directory.inbox.drain() if e.platform == "uav-b"]
        assert told == [], told
        directory.close()
