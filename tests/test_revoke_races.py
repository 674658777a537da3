"""Revocation at a running platform: what races it, what it must end, what it must not
count twice (the example station's platforms, in process)."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from _node_example import Station

from agents import (
    ACLMessage,
    Agent,
    KeyPair,
    Performative,
    ServiceDescription,
    TrustStore,
    Visibility,
)
from tests.test_sharing_reload import _until

if TYPE_CHECKING:
    from federation import FederationPlatform

CONFIG = "station-python.toml"


def _pair(tmp_path: Path) -> tuple[FederationPlatform, FederationPlatform]:
    """The example's station and operator platforms (not started)."""
    from federation import FederationPlatform

    station = Station(tmp_path)
    s = FederationPlatform.from_file(station.dir / CONFIG)
    o = FederationPlatform.from_file(station.dir / "operator.toml")
    return s, o


def _hello(p: FederationPlatform, to: str) -> ACLMessage:
    """A harmless message for ``to``'s Interface Agent (a session announcement)."""
    agent = p.interface.agent
    assert agent is not None
    return agent.message(
        Performative.INFORM, f"interface@{to}", {"session": "new"}, ontology="interface"
    )


@pytest.mark.timeout(90)
async def test_a_send_awaiting_its_key_exchange_when_revoked_is_dropped_not_raised(
    tmp_path: Path,
) -> None:
    from federation._cli_common import wait_for_members

    s, o = _pair(tmp_path)
    async with asyncio.timeout(80), s, o:
        assert await wait_for_members(o, "station", 30)
        assert await wait_for_members(s, "operator", 30)
        s.interface.sessions.forget("operator")  # the next send agrees a session first
        send = asyncio.create_task(s.interface.send("operator", _hello(s, "operator")))
        while "operator" not in s.interface._handshakes:  # noqa: ASYNC110  (no event)
            await asyncio.sleep(0)
        assert s.interface.trust.remove("operator")  # while its key exchange runs
        await send  # dropped and counted, as a send after the revocation: never raised
        assert s.interface.unsent_revoked == 1
        assert s.interface.sessions.session_for("operator") is None


@pytest.mark.timeout(90)
async def test_a_platform_trusted_again_is_sent_to_again(tmp_path: Path) -> None:
    from federation._cli_common import wait_for_members

    s, o = _pair(tmp_path)
    async with asyncio.timeout(80), s, o:
        assert await wait_for_members(o, "station", 30)
        key = s.interface.trust.public_key("operator")
        assert s.interface.trust.remove("operator")
        await s.interface.send("operator", _hello(s, "operator"))
        assert s.interface.unsent_revoked == 1
        assert s.interface.trust.add("operator", key)
        await s.interface.send("operator", _hello(s, "operator"))
        assert s.interface.unsent_revoked == 1  # not stuck: sent after a new key exchange
        assert s.interface.sessions.session_for("operator") is not None


@pytest.mark.timeout(90)
async def test_an_import_ended_before_the_revocation_is_not_ended_again(tmp_path: Path) -> None:
    from federation._cli_common import wait_for_members

    s, o = _pair(tmp_path)
    async with asyncio.timeout(80), s, o:
        source = s.instance.add_source("wx/temperature")
        assert await wait_for_members(o, "station", 30)
        await o.federation_agent.create_stream("station", ["temperature"], timeout=10)
        [export] = s.exporter.exports("operator")
        imported = o.importer.get("station", "temperature")
        assert imported is not None
        source.push(20.0)
        await _until("a sample imported", lambda: imported.received > 0)
        await s.exporter.stop(export, why="done")  # the station ends it: told, ended there
        await _until("the import ended", lambda: imported.ended)
        assert o.importer.imports("station") == [imported]  # kept, ended
        assert o.interface.trust.remove("station")
        await _until("the import forgotten", lambda: o.importer.imports("station") == [])
        ended = [r for r in o.interface.audit.records if r.get("verdict") == "ended"]
        assert o.revoked_imports == 0 and ended == [], (o.revoked_imports, ended)


@pytest.mark.timeout(90)
async def test_a_revoked_platforms_directory_subscription_ends(tmp_path: Path) -> None:
    from agents._df import subscribe_services
    from federation._cli_common import wait_for_members

    s, o = _pair(tmp_path)
    async with asyncio.timeout(80), s, o:
        assert await wait_for_members(o, "station", 30)
        df = s.agents.df
        assert df is not None
        remote = await o.agents.add(Agent("remote"))
        await subscribe_services(remote, df="df@station")
        held = [k for k in df._subscriptions.subscribers if k[0].endswith("@operator")]
        assert held
        assert s.interface.trust.remove("operator")
        for i in range(3):
            await df.register(
                ServiceDescription(
                    name=f"svc{i}", type="t", provider="x@station", visibility=Visibility.PUBLIC
                )
            )
        # what it held at the DF ends with its revocation, as at the gateway; else each
        # change is one more `unsent_revoked`, and informs resume to whoever holds its
        # name next (a rekey)
        held = [k for k in df._subscriptions.subscribers if k[0].endswith("@operator")]
        assert held == [], (held, s.interface.unsent_revoked)
        assert s.interface.unsent_revoked == 0  # no inform of the changes was even tried
        (record,) = [r for r in s.interface.audit.records if r.get("verdict") == "revoked"]
        assert "1 directory subscription(s) of it ended" in record["reason"]


@pytest.mark.timeout(90)
async def test_a_revoked_platform_leaves_the_directory_and_the_members(tmp_path: Path) -> None:
    from federation._cli_common import wait_for_members

    s, o = _pair(tmp_path)
    async with asyncio.timeout(80), s, o:
        assert await wait_for_members(s, "operator", 30)
        gdf = s.agents.global_df
        assert gdf is not None
        assert "operator" in gdf.platforms
        assert s.interface.trust.remove("operator")
        await _until(
            "the revoked platform out of the members and the directory",
            lambda: (
                "operator" not in s.federation_agent.members and "operator" not in gdf.platforms
            ),
            5,
        )
        assert gdf.services("operator") == []
        # it does not come back while revoked: its token still holds, but nothing of it is
        # trusted (its snapshots and events are signed with a key no longer in the file)
        await asyncio.sleep(1.0)  # the directory's re-checks: nothing to await, a bounded look
        assert "operator" not in gdf.platforms and "operator" not in s.federation_agent.members


@pytest.mark.timeout(90)
async def test_a_platform_rekeyed_from_another_thread_gets_nothing_sealed_on_its_old_session(
    tmp_path: Path,
) -> None:
    """A trust reload (SIGHUP's, on its own thread) gives the operator another key while the
    loop is busy: before the revocation reaches the loop, what the loop sends is not sealed
    on the session agreed with the old key; a key exchange is needed, and the one under the
    new key fails (the operator cannot sign with it), as a send with no session does."""
    import threading

    from agents import KeyPair, SecurityError, TrustStore, UnknownSession
    from federation._cli_common import wait_for_members

    s, o = _pair(tmp_path)
    async with asyncio.timeout(80), s, o:
        assert await wait_for_members(o, "station", 30)
        await s.interface.send("operator", _hello(s, "operator"))
        await _until("the turn's batch closed", lambda: "operator" not in s.interface._outbox)
        assert s.interface.sessions.session_for("operator") is not None
        trust = s.interface.trust
        new = TrustStore(
            trust.federation,
            {
                "station": trust.public_key("station"),
                "operator": KeyPair.generate("operator").public_key,
            },
        )
        # joined here: the loop is held, as a busy one is, so the revocation waits for it
        worker = threading.Thread(target=s.reload_trust, args=(new,))
        worker.start()
        worker.join(10)
        assert not worker.is_alive()
        assert s.interface.revoked == 0  # not yet on the loop
        assert s.interface.sessions.session_for("operator") is None
        with pytest.raises(UnknownSession):
            s.interface.sessions.seal("operator", b"{}")
        assert not s.interface.send_now("operator", _hello(s, "operator"))
        with pytest.raises(SecurityError, match="key exchange with 'operator' refused"):
            await s.interface.send("operator", _hello(s, "operator"))
        await _until("the revocation", lambda: s.interface.revoked == 1)
        (record,) = [r for r in s.interface.audit.records if r.get("verdict") == "revoked"]
        assert record["to"] == "operator"


@pytest.mark.timeout(90)
async def test_a_batch_waiting_as_its_platform_is_rekeyed_is_lost_and_counted(
    tmp_path: Path,
) -> None:
    """A batch for the operator waits for its turn's end as a trust reload (SIGHUP's own
    thread) gives the operator another key: it is not sealed on the old key's session,
    and it is lost and counted in ``batches_lost`` (docs/security.md), not dropped
    unsaid; the revocation that follows finds nothing more of it waiting."""
    import threading

    from federation._cli_common import wait_for_members

    s, o = _pair(tmp_path)
    async with asyncio.timeout(80), s, o:
        assert await wait_for_members(o, "station", 30)
        ia = s.interface
        await ia.send("operator", _hello(s, "operator"))  # a session agreed
        await _until("the turn's batch closed", lambda: "operator" not in ia._outbox)
        await ia.send("operator", _hello(s, "operator"))  # alone: the turn's batch opens
        assert ia.join_batch("operator", _hello(s, "operator"))  # waits for the turn's end
        trust = ia.trust
        new = TrustStore(
            trust.federation,
            {
                "station": trust.public_key("station"),
                "operator": KeyPair.generate("operator").public_key,
            },
        )
        lost, unsent = ia.batches_lost, ia.unsent_revoked
        worker = threading.Thread(target=s.reload_trust, args=(new,))
        worker.start()
        worker.join(10)  # the loop held meanwhile, as a busy one is
        assert not worker.is_alive()
        assert "operator" in ia._outbox and ia.revoked == 0
        await _until("the batch's turn ended", lambda: "operator" not in ia._outbox)
        assert ia.batches_lost == lost + 1
        await _until("the revocation", lambda: ia.revoked == 1)
        assert ia.unsent_revoked == unsent
        assert ia.sessions.session_for("operator") is None
