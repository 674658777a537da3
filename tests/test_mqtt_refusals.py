"""What the MQTT transport does when the broker refuses a subscription, or answers late.

Mosquitto 2.0 grants a subscription its ACL denies: the `Relay` of
``tests/test_mqtt_start_close.py`` rewrites the SUBACK's reason codes as a strict broker
would send them.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import socket
import struct
import subprocess
import uuid
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from agents import AgentPlatform
from agents._exceptions import TransportError
from agents.keys import gen_keys, trust_keys
from agents.transports import MqttConfig, MqttTransport
from agents.transports._mqtt import query_topic
from federation import FederationPlatform, PlatformConfig
from tests._node_example import Station
from tests.test_mqtt_start_close import WAIT, Relay


class _Relay(Relay):
    """A `Relay` serving on ``listening``, with the clients a test makes through and beside it."""

    listening: int

    def through(self, **options: Any) -> MqttTransport:
        """A transport to the broker through the relay (``options``: its `MqttConfig`'s)."""
        return MqttTransport(MqttConfig(host="127.0.0.1", port=self.listening, **options))

    def beside(self) -> MqttTransport:
        """A transport straight to the broker, which the relay's steering does not touch."""
        return MqttTransport(MqttConfig(host=self.host, port=self.port))

    def reset(self) -> None:
        """`drop`, each connection reset (RST) rather than closed: a network that failed."""
        for writer in list(self.writers):
            sock = writer.get_extra_info("socket")
            if sock is not None:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        self.drop()


@pytest.fixture
async def relay(mosquitto: tuple[str, int]) -> AsyncIterator[_Relay]:
    """A running relay to the session's broker (`Relay`), closed after the test."""
    relay = _Relay(*mosquitto)
    async with relay.running() as listening:
        relay.listening = listening
        yield relay


async def test_a_token_whose_own_subscription_is_refused_is_not_declared(relay: _Relay) -> None:
    # the token subscribes to its key (to announce again when another client clears it):
    # its SUBACK was not read, a refused one taken as granted, the token alive with
    # nobody listening for its clearing
    u = uuid.uuid4().hex
    key = f"alive/{u}/x"
    relay.refuse[key] = 0x87  # not authorized
    async with relay.through() as t, relay.beside() as watcher:
        handles = set(t._handles)
        with pytest.raises(TransportError) as refused:
            async with asyncio.timeout(WAIT):
                await t.declare_token(key)
        assert str(refused.value) == (
            f"mqtt: the broker refused the subscription to {key!r}: Not authorized (0x87)"
        )
        assert t._handles == handles
        await relay.wait_for(lambda: relay.open == 1)  # the token's connection closed
        assert await watcher.tokens(f"alive/{u}/*", timeout=WAIT) == []  # never announced
        # granted, the same key is declared and seen alive
        del relay.refuse[key]
        async with asyncio.timeout(WAIT), await t.declare_token(key):
            assert await watcher.tokens(f"alive/{u}/*", timeout=WAIT) == [key]


async def test_answers_later_than_connect_timeout_log_no_error(
    own_mosquitto: tuple[str, int, subprocess.Popen[bytes]], caplog: pytest.LogCaptureFixture
) -> None:
    # a broker stalled past connect_timeout: the subscribe's wait (and then the
    # unsubscribe's) timed out, aiomqtt forgot the packet ids, and the SUBACK and UNSUBACK
    # that came once the broker ran again were logged at ERROR ("Unexpected message ID")
    host, port, broker = own_mosquitto
    key = f"late/{uuid.uuid4().hex}"
    caplog.set_level(logging.DEBUG)
    async with (
        MqttTransport(MqttConfig(host=host, port=port, connect_timeout=0.3)) as t,
        MqttTransport(MqttConfig(host=host, port=port)) as sender,
    ):
        broker.send_signal(signal.SIGSTOP)
        try:
            with pytest.raises(TransportError, match="timed out"):
                async with asyncio.timeout(WAIT):
                    await t.subscribe(key)
            unsubscribing = t._unsubscribing[key]  # the filter given up, in the background
            async with asyncio.timeout(WAIT):
                await asyncio.wait([unsubscribing])  # which times out too
        finally:
            broker.send_signal(signal.SIGCONT)
        # the broker answers both late, then this subscribe, in order: running again, but
        # on a loaded machine maybe not within the 0.3 s that only had to outlast the stall
        assert t._client is not None
        t._client.timeout = WAIT
        async with asyncio.timeout(WAIT):
            sub = await t.subscribe(key)
        async with sub:
            await sender.publish(key, b"after")
            assert (await sub.get(timeout=WAIT)).payload == b"after"
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert errors == []
    late = [r.getMessage() for r in caplog.records if "after it was given up" in r.getMessage()]
    assert [m.split()[4] for m in late] == ["subscribe", "unsubscribe"]


async def test_an_answer_to_a_call_never_made_is_still_logged_as_unexpected(
    relay: _Relay, caplog: pytest.LogCaptureFixture
) -> None:
    # only an answer to a call given up is late: a SUBACK whose packet id no call of
    # this client ever had (a broker's bug, a stream gone wrong) was logged at DEBUG as
    # "given up", hiding what aiomqtt reports as an error
    key = f"forged/{uuid.uuid4().hex}"
    caplog.set_level(logging.DEBUG)
    async with relay.through() as t, relay.beside() as sender:
        relay.forge = b"\x90\x04\xbe\xef\x00\x00"  # a SUBACK for packet id 0xBEEF, granted
        async with asyncio.timeout(WAIT):
            sub = await t.subscribe(key)
        async with sub:
            # read after the forged SUBACK, which came right behind the real one
            await sender.publish(key, b"after")
            assert (await sub.get(timeout=WAIT)).payload == b"after"
    unexpected = [
        r for r in caplog.records if r.levelno >= logging.ERROR and "48879" in r.getMessage()
    ]
    assert [r.getMessage() for r in unexpected] == [
        'Unexpected message ID "48879" in on_subscribe callback'
    ]
    assert not [r for r in caplog.records if "after it was given up" in r.getMessage()]


async def test_a_token_whose_reconnection_fails_ends_and_is_not_cleared_on_a_lost_connection(
    relay: _Relay, caplog: pytest.LogCaptureFixture
) -> None:
    # ended, its handle closed, it was "cleared" on the connection already lost: a
    # warning that the token could not be cleared, which reads as a key left alive
    key = f"alive/{uuid.uuid4().hex}/x"
    caplog.set_level(logging.WARNING, logger="agents.transports._mqtt")
    async with relay.through(connect_timeout=1.0) as t:
        handle = await t.declare_token(key)
        told: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        handle.on_end(told.set_result)
        relay.stall = True  # the reconnections are never answered
        relay.drop()
        async with asyncio.timeout(WAIT):
            reason = await told
        # ended by whichever fails first: the transport's reconnection (as a rule: the
        # token's waits for it) or the token's own
        lost = reason.startswith("mqtt: the connection to the broker was lost (")
        lost = lost and "and could not be made again (" in reason
        own = reason.startswith(f"mqtt: connect for the token on {key!r}: ")
        assert lost or (own and reason.endswith("(after reconnecting)")), reason
        assert handle.closed and handle.ended == reason
        clearing = [x for x in asyncio.all_tasks() if x.get_name() == f"mqtt.token[{key}].clear"]
        async with asyncio.timeout(WAIT):
            await asyncio.gather(*clearing)
            await relay.wait_for(lambda: relay.open == 0)  # every connection closed
    assert not [r for r in caplog.records if "could not clear" in r.getMessage()]


async def test_a_queryable_refused_after_a_reconnection_ends_and_its_owner_is_told(
    relay: _Relay, caplog: pytest.LogCaptureFixture
) -> None:
    # subscribed anew after a reconnection, a queryable's refused filter was only logged:
    # its owner believed it served, and queries through that filter went unanswered
    u = uuid.uuid4().hex
    key = f"q/{u}/x"
    caplog.set_level(logging.WARNING, logger="agents.transports._mqtt")

    async def answer(key: str, payload: bytes) -> bytes:
        return b"here"

    async with relay.through() as t, relay.beside() as asker:
        kept = await t.serve(f"kept/{u}", answer)
        handle = await t.serve(key, answer)
        told: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        handle.on_end(told.set_result)
        assert (await asker.query(key, timeout=1.0))[0].payload == b"here"
        relay.refuse[f"@query/q/{u}/x"] = 0x87  # not authorized
        relay.drop()
        async with asyncio.timeout(WAIT):
            reason = await told
        assert reason == (
            f"mqtt: the broker refused the subscription to '@query/q/{u}/x': "
            "Not authorized (0x87) (after reconnecting)"
        )
        assert handle.closed and handle.ended == reason
        assert handle not in t._handles
        # ended whole: none of its filters is left, the other queryable's are
        assert not [topic for topic in t._filters if u in topic and "kept" not in topic]
        assert f"@query/kept/{u}" in t._filters
        late: list[str] = []
        handle.on_end(late.append)  # told at once when it ended already
        assert late == [reason]
        assert t._up is not None
        async with asyncio.timeout(WAIT):
            await t._up.wait()  # reconnected, the other filters subscribed again
            assert t.reconnects == 1
            assert [r.payload for r in await asker.query(f"kept/{u}", timeout=1.0)] == [b"here"]
            assert await asker.query(key, timeout=0.5) == []  # nobody serves it any more
        handle.close()  # closing what ended already is harmless
        await kept.aclose()


async def test_a_token_refused_after_a_reconnection_ends_and_its_owner_is_told(
    relay: _Relay,
) -> None:
    # a token that could not announce itself again after its connection dropped was only
    # logged: its owner believed it alive while nobody saw it
    u = uuid.uuid4().hex
    key = f"alive/{u}/x"
    async with relay.through() as t:
        handle = await t.declare_token(key)
        told: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        handle.on_end(told.set_result)
        relay.refuse[key] = 0x87  # not authorized
        relay.drop()
        async with asyncio.timeout(WAIT):
            reason = await told
        assert reason == (
            f"mqtt: the broker refused the subscription to {key!r}: Not authorized (0x87)"
            " (after reconnecting)"
        )
        assert handle.closed and handle.ended == reason
        assert handle not in t._handles
        async with asyncio.timeout(WAIT):
            await handle.aclose()  # closing what ended already is harmless


async def test_a_platform_whose_directory_is_refused_after_a_reconnection_says_so_and_counts_it(
    relay: _Relay, caplog: pytest.LogCaptureFixture
) -> None:
    # the transport ended the directory's queryable, and nothing of the platform's heard:
    # it ran on, believing its agents findable, while others' directory queries went
    # unanswered, with not a line in its log
    fed = f"lost-{uuid.uuid4().hex[:8]}"
    caplog.set_level(logging.ERROR)
    async with (
        relay.through() as t,
        relay.beside() as other,
        AgentPlatform("uav-a", t, federation=fed) as p,
    ):
        key = p.key("df")
        assert await other.query(key, timeout=WAIT)  # served: an answer, whatever it says
        told: asyncio.Future[tuple[str, str]] = asyncio.get_running_loop().create_future()
        p.on_lost(lambda what, why: told.done() or told.set_result((what, why)))
        assert p.stats.declarations_lost == 0 and p.lost == {}
        relay.refuse[f"@query/{key}"] = 0x87  # not authorized, from the reconnection on
        relay.drop()
        async with asyncio.timeout(WAIT):
            what, reason = await told
        assert what == f"directory queryable {key}"
        assert reason == (
            f"mqtt: the broker refused the subscription to '@query/{key}': "
            "Not authorized (0x87) (after reconnecting)"
        )
        assert p.stats.declarations_lost == 1 and p.lost == {what: reason}
        errors = [(r.name, r.getMessage()) for r in caplog.records if r.levelno >= logging.ERROR]
        assert errors == [
            (
                "agents._platform",
                f"platform[uav-a]: lost its {what} ({reason}): other platforms can no longer "
                "find this platform's agents (their directory queries go unanswered)",
            )
        ]
        late: list[tuple[str, str]] = []
        p.on_lost(lambda what, why: late.append((what, why)))  # told at once of the past
        assert late == [(what, reason)]
        # what it means, seen from another platform: the platform is alive, its
        # directory silent
        assert t._up is not None
        async with asyncio.timeout(WAIT):
            await t._up.wait()
        async with asyncio.timeout(WAIT):  # the token announced again, in its own time
            # each ask returns once its round trip through the broker is back: its bound
            # is that of a loaded broker's answer, not 0.2 s (then it raised)
            while await other.tokens(p.key("alive", "*"), timeout=WAIT) != [p.key("alive")]:
                pass
        assert await other.query(key, timeout=0.5) == []
    # its close is clean, the ended queryable closed again harmlessly (the relay's own
    # cancelled connections are asyncio's to log)
    ours = [r for r in caplog.records if r.name.startswith(("agents", "federation"))]
    assert [(r.name, r.getMessage()) for r in ours if r.levelno >= logging.ERROR] == errors


async def test_a_platform_whose_inbox_is_refused_after_a_reconnection_says_so_and_counts_it(
    relay: _Relay, caplog: pytest.LogCaptureFixture
) -> None:
    # its inbox's subscription ended, its consumer with it: the platform ran on deaf to
    # every other platform's messages, nothing counted, nothing at ERROR, a node up
    fed = f"deaf-{uuid.uuid4().hex[:8]}"
    caplog.set_level(logging.ERROR)
    async with relay.through() as t, AgentPlatform("uav-a", t, federation=fed) as p:
        told: asyncio.Future[tuple[str, str]] = asyncio.get_running_loop().create_future()
        p.on_lost(lambda what, why: told.done() or told.set_result((what, why)))
        key = p.key("acl")
        relay.refuse[key] = 0x87  # not authorized, from the reconnection on
        relay.drop()
        async with asyncio.timeout(WAIT):
            what, reason = await told
        assert (what, reason) == (
            f"inbox subscription {key}",
            "the transport ended the subscription",
        )
        assert p.stats.declarations_lost == 1 and p.lost == {what: reason}
        errors = [(r.name, r.getMessage()) for r in caplog.records if r.levelno >= logging.ERROR]
        assert (
            "agents._platform",
            f"platform[uav-a]: lost its {what} ({reason}): other platforms' messages to this "
            "platform's agents are no longer received",
        ) in errors
    # closed, as every close closes it: no loss
    assert p.stats.declarations_lost == 1


async def test_a_platform_whose_broker_cannot_be_reached_again_loses_every_declaration(
    relay: _Relay,
) -> None:
    # a broker restarting: the one reconnection of the platform's connection failed, the
    # transport was lost, nothing answered any more, but no declaration ended: the
    # token's own connection, made once the broker was back, announced the platform
    # alive again, and neither the platform nor a node running it heard of anything
    fed = f"gone-{uuid.uuid4().hex[:8]}"
    async with (
        relay.through(connect_timeout=5.0) as t,
        relay.beside() as other,
        AgentPlatform("uav-a", t, federation=fed) as p,
    ):
        alive = p.key("alive")
        assert await other.tokens(p.key("alive", "*"), timeout=WAIT) == [alive]
        told: asyncio.Queue[str] = asyncio.Queue()
        p.on_lost(lambda what, why: told.put_nowait(what))
        relay.down = True  # the connections made again are closed at once
        relay.drop()
        # the reconnection waits connect_timeout for its CONNACK before it fails
        async with asyncio.timeout(WAIT + t.config.connect_timeout):
            lost = {await told.get() for _ in range(5)}
        inbox, df = f"inbox subscription {p.key('acl')}", f"directory queryable {p.key('df')}"
        presence = f"directory presence watch {p.key('alive', '*')}"
        events = f"directory events subscription {p.key('df-events', '*')}"
        assert lost == {f"liveliness token {alive}", df, inbox, presence, events}
        assert p.stats.declarations_lost == 5
        for ended in (inbox, presence, events):
            assert p.lost[ended] == "the transport ended the subscription"
        assert p.lost[df].startswith("mqtt: the connection to the broker was lost (")
        # the token by the same loss, or by its own reconnection when that failed first
        # (each waits connect_timeout for a connection the relay closes at once)
        relay.down = False  # the broker back: nothing of the platform's comes back with it
        clearing = [x for x in asyncio.all_tasks() if x.get_name() == f"mqtt.token[{alive}].clear"]
        async with asyncio.timeout(WAIT):
            await asyncio.gather(*clearing)
        assert await other.tokens(p.key("alive", "*"), timeout=WAIT) == []


def _over_mqtt(conf: Path, port: int, to: Path | None = None) -> None:
    """``conf``'s ``[transport]`` as MQTT on 127.0.0.1:``port`` (written to ``to``, else to it)."""
    text = conf.read_text()
    start = text.index("[transport]")
    end = text.index("\n[", start)  # its inputs follow
    (to or conf).write_text(
        f'{text[:start]}[transport]\nkind = "mqtt"\nhost = "127.0.0.1"\nport = {port}\n'
        f'client_id = "station-{uuid.uuid4().hex[:8]}"\n{text[end:]}'
    )


async def test_a_node_whose_directory_is_refused_after_a_reconnection_stops_cleanly_and_exits_1(
    tmp_path: Path, relay: _Relay
) -> None:
    # a real `dyknow node` over MQTT: it ran on with its directory unserved, silent; now
    # it says what it lost and what that means, closes cleanly (its presence cleared,
    # its figures said) and exits 1, for its supervisor to start it again
    station = Station(tmp_path)
    conf = station.dir / "station-python.toml"
    fed = station.federation
    df = f"dyknow/{fed}/v1/df/station"
    loop = asyncio.get_running_loop()
    async with relay.beside() as other:
        _over_mqtt(conf, relay.listening)
        node = station.spawn("node", "--config", conf.name)
        station.node = node
        try:
            assert node.stdout is not None
            async with asyncio.timeout(3 * WAIT):
                ready = await loop.run_in_executor(None, node.stdout.readline)
            assert f"station ready in federation {fed}" in ready, station.stop()
            assert await other.query(df, timeout=WAIT)  # its directory answers
            relay.refuse[f"@query/{df}"] = 0x87  # not authorized, from the reconnection on
            relay.drop()
            async with asyncio.timeout(3 * WAIT):
                out, err = await loop.run_in_executor(None, node.communicate)
        finally:
            if node.poll() is None:
                station.stop()
            station.node = None
        assert node.returncode == 1, (out, err)
        reason = (
            f"mqtt: the broker refused the subscription to '@query/{df}': "
            "Not authorized (0x87) (after reconnecting)"
        )
        lines = err.splitlines()
        assert "Traceback" not in err, err
        # the log's line, the node's word that it stops, and the exit's reason, in order
        # the log's records say their level and logger, apart from the node's own lines
        drop = "WARNING agents.transports._mqtt: mqtt: connection to the broker lost ("
        assert [line for line in lines if line.startswith(drop)], err
        ours = [line for line in lines if line.startswith(("ERROR ", "dyknow node:"))]
        assert ours == [
            f"ERROR agents._platform: platform[station]: lost its directory queryable {df} "
            f"({reason}): other platforms can no longer find this platform's agents (their "
            "directory queries go unanswered)",
            "dyknow node: station stopping, to exit with code 1 for its supervisor to "
            f"restart it: the transport ended its directory queryable {df}",
            f"dyknow node: {conf.name}: platform 'station' stopped: the transport ended its "
            f"directory queryable {df} ({reason}). Started again, it declares them anew",
        ], err
        said = out.splitlines()
        assert f"dyknow node: declarations lost: 1 (directory queryable {df})" in said, out
        assert said[-1] == "dyknow node: station stopped", out
        # closed cleanly: its presence cleared (it left, not merely went silent)
        assert await other.tokens(f"dyknow/{fed}/v1/alive/*", timeout=WAIT) == []


async def test_a_platform_whose_presence_and_events_are_refused_after_a_reconnection_says_so(
    relay: _Relay, caplog: pytest.LogCaptureFixture
) -> None:
    # its directory's presence watch and events subscription ended, their consumers with
    # them: the platform ran on no longer seeing others come and go nor their directories
    # change, with nothing at ERROR, nothing counted, a node up
    fed = f"blind-{uuid.uuid4().hex[:8]}"
    caplog.set_level(logging.ERROR)
    async with relay.through() as t, AgentPlatform("uav-a", t, federation=fed) as p:
        told: asyncio.Queue[tuple[str, str]] = asyncio.Queue()
        p.on_lost(lambda what, why: told.put_nowait((what, why)))
        presence, events = p.key("alive", "*"), p.key("df-events", "*")
        relay.refuse[presence.replace("*", "+")] = 0x87  # not authorized, from the
        relay.refuse[events.replace("*", "+")] = 0x87  # reconnection on
        relay.drop()
        async with asyncio.timeout(WAIT):
            lost = dict([await told.get(), await told.get()])
        ended = "the transport ended the subscription"
        assert lost == {
            f"directory presence watch {presence}": ended,
            f"directory events subscription {events}": ended,
        }
        assert p.stats.declarations_lost == 2 and p.lost == lost
        errors = {r.getMessage() for r in caplog.records if r.name == "agents._platform"}
        assert errors == {
            f"platform[uav-a]: lost its directory presence watch {presence} ({ended}): other "
            "platforms coming and going are no longer seen but by their signed leaves and the "
            "directory's rechecks (where they run): till then one that goes without its signed "
            "leave (a crash) stays in this platform's directory, one that comes is not added "
            "to it",
            f"platform[uav-a]: lost its directory events subscription {events} ({ended}): "
            "other platforms' directory changes (services added, removed, a signed leave) "
            "are no longer followed: this platform's directory of their services goes stale",
        }
    # closed, as every close closes them: no loss
    assert p.stats.declarations_lost == 2


async def test_a_platform_whose_streams_and_loss_reports_are_refused_says_so_and_counts_it(
    tmp_path: Path,
    relay: _Relay,
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the import proxy's streams subscription and the export proxy's loss reports ended,
    # their consumers with them: the platform ran on receiving no other platform's
    # streams, its exports deaf to their receivers, nothing at ERROR, a node up
    fed = f"streamless-{uuid.uuid4().hex[:8]}"
    pub = gen_keys("uav-a", tmp_path / "keys")[2]
    trust_keys(tmp_path / "trust.json", [pub], federation=fed)
    config = PlatformConfig(
        name="uav-a",
        federation=fed,
        key=tmp_path / "keys" / "uav-a.key",
        trust=tmp_path / "trust.json",
        vocabulary={"name": "t", "labels": {"speed": "speed"}},
        mapping={"vocabulary": "t", "labels": {"speed": "local/speed"}},
    )
    caplog.set_level(logging.ERROR)
    async with relay.through() as t, FederationPlatform(config, transport=t, join=False) as p:
        told: asyncio.Queue[tuple[str, str]] = asyncio.Queue()
        p.agents.on_lost(lambda what, why: told.put_nowait((what, why)))
        streams = p.agents.key("stream") + "/*/**"
        reports = p.agents.key("stream-report") + "/*"
        granted = asyncio.Event()
        subscribe = t.subscribe

        async def subscribed(key: str, **options: Any) -> Any:
            sub = await subscribe(key, **options)
            if key == reports:
                granted.set()
            return sub

        monkeypatch.setattr(t, "subscribe", subscribed)
        p.instance.add_source("local/speed")
        # the loss reports are subscribed to with the first export
        p.exporter.start_exporting("local/speed", "speed", "uav-b")
        # granted before the connection drops (else its first subscribe fails instead)
        async with asyncio.timeout(WAIT):
            await granted.wait()
        relay.refuse[streams.replace("/*/**", "/+/#")] = 0x87  # not authorized, from the
        relay.refuse[reports.replace("*", "+")] = 0x87  # reconnection on
        relay.drop()
        async with asyncio.timeout(WAIT):
            lost = dict([await told.get(), await told.get()])
        ended = "the transport ended the subscription"
        assert lost == {
            f"streams subscription {streams}": ended,
            f"loss reports subscription {reports}": ended,
        }
        assert p.agents.stats.declarations_lost == 2 and p.agents.lost == lost
        errors = {r.getMessage() for r in caplog.records if r.name == "agents._platform"}
        assert errors == {
            f"platform[uav-a]: lost its streams subscription {streams} ({ended}): other "
            "platforms' streams to this platform are no longer received: its imports get no "
            "more samples and count none lost, while its loss reports still renew their "
            "senders' leases (the senders go on exporting)",
            f"platform[uav-a]: lost its loss reports subscription {reports} ({ended}): "
            "receivers' loss reports are not heard until the subscription is made again "
            "(tried with backoff): meanwhile this platform's exports may end at their lease "
            "as if their receivers were gone, their losses in transit not counted nor resent",
        }
    # closed, as every close closes them: no loss
    assert p.agents.stats.declarations_lost == 2


@pytest.mark.parametrize("ended", ["refused", "broker gone", "connection reset"])
async def test_an_owners_watch_whose_subscriptions_the_transport_ends_says_so_and_exits_1(
    tmp_path: Path, relay: _Relay, ended: str
) -> None:
    # a real `dyknow watch` over MQTT: its subscription refused after a reconnection, or
    # its connection lost and not made again, its pumps ended and it exited 0 as after
    # --duration, silent: an owner piping it saw a quiet platform, not a blind watch
    station = Station(tmp_path)
    conf = station.dir / "station-python.toml"
    fed = station.federation
    watch_key, audit_key = f"dyknow/{fed}/v1/watch/station", f"dyknow/{fed}/v1/audit/station"
    loop = asyncio.get_running_loop()
    # the node straight to the broker, its owner's watch through the relay
    _over_mqtt(conf, relay.listening, station.dir / "watch.toml")
    _over_mqtt(conf, relay.port)
    station.start("python")
    watch = station.spawn("watch", "--config", "watch.toml")
    try:
        assert watch.stdout is not None
        async with asyncio.timeout(3 * WAIT):
            first = await loop.run_in_executor(None, watch.stdout.readline)
        assert first.startswith("watching station"), first
        if ended == "refused":
            relay.refuse[watch_key] = 0x87  # not authorized, from the reconnection on
        else:
            relay.down = True  # the connections made again are closed at once
        if ended == "connection reset":
            relay.reset()  # the client's read fails (paho logs it at ERROR, "mqtt")
        else:
            relay.drop()
        async with asyncio.timeout(3 * WAIT):
            out, err = await loop.run_in_executor(None, watch.communicate)
    finally:
        if watch.poll() is None:
            watch.kill()
            watch.communicate()
        node_out, _ = station.stop()
    assert watch.returncode == 1, (out, err)
    assert "Traceback" not in err, err
    lines = err.splitlines()
    drop = "WARNING agents.transports._mqtt: mqtt: connection to the broker lost ("
    assert [line for line in lines if line.startswith(drop)], err
    ended_sub = "the transport ended the subscription"
    watching = (
        f"watch subscription {watch_key}",
        "the messages, batches and reports the platform opens are no longer shown",
    )
    auditing = (
        f"audit subscription {audit_key}",
        "the platform's audit records are no longer shown",
    )
    lost = [watching] if ended == "refused" else [watching, auditing]
    # the loss said once, by the transport's warning above: not again by paho's ERROR
    # ("failed to receive on socket: [Errno 104] …", logger "mqtt")
    assert not [line for line in lines if line.startswith("ERROR mqtt")], err
    ours = [line for line in lines if line.startswith(("ERROR federation", "dyknow:"))]
    assert ours == [
        *(
            f"ERROR federation._cli_net: watch[station]: lost its {what} ({ended_sub}): {meaning}"
            for what, meaning in lost
        ),
        f"dyknow: the watch of platform 'station' stopped: the transport ended its "
        f"{', its '.join(what for what, _ in lost)} ({ended_sub}). Run again, it subscribes anew",
    ], err
    # a renewal asked while the transport reconnected is said once, and ends nothing
    assert len([line for line in lines if "the watch not renewed" in line]) <= 1, err
    # the node saw nothing of it: its owner's watch is no declaration of its
    assert "declarations lost" not in node_out, node_out


async def test_an_owners_watch_whose_renewal_the_broker_takes_and_never_acknowledges_ends(
    tmp_path: Path, relay: _Relay
) -> None:
    # a broker that takes the renewal's PUBLISH (QoS 1) and never acknowledges it, the
    # connection up all along: each renewal failed ("Operation timed out"), said once,
    # then asked again for ever, the platform's lease long run out: the watch ran on,
    # blind, as a quiet platform looks
    station = Station(tmp_path)
    conf = station.dir / "station-python.toml"
    fed = station.federation
    watch_key = f"dyknow/{fed}/v1/watch/station"
    loop = asyncio.get_running_loop()
    _over_mqtt(conf, relay.listening, station.dir / "watch.toml")
    watch_conf = station.dir / "watch.toml"
    watch_conf.write_text(
        watch_conf.read_text().replace(
            "[transport]\n", "[transport]\nqos = 1\nconnect_timeout = 1.0\n", 1
        )
    )
    _over_mqtt(conf, relay.port)
    station.start("python")
    watch = station.spawn("watch", "--config", "watch.toml")
    try:
        assert watch.stdout is not None
        async with asyncio.timeout(3 * WAIT):
            first = await loop.run_in_executor(None, watch.stdout.readline)
        assert first.startswith("watching station"), first
        relay.swallow = (query_topic(watch_key),)

        def ended() -> tuple[str, str]:
            # renewed every 3 s, the watch gives the platform 10 s (--timeout) as it
            # does for the first answer
            try:
                return watch.communicate(timeout=10 + 3 * WAIT)
            except subprocess.TimeoutExpired:
                watch.kill()
                out, err = watch.communicate()
                return out, f"still running, killed\n{err}"

        out, err = await loop.run_in_executor(None, ended)
    finally:
        if watch.poll() is None:
            watch.kill()
            watch.wait()
        station.stop()
    assert watch.returncode == 1, (out, err)
    assert "Traceback" not in err, err
    lines = err.splitlines()
    assert len([line for line in lines if "the watch not renewed" in line]) == 1, err
    assert lines[-1].startswith(
        "dyknow: TransportError: platform 'station': the watch was not renewed in 10 s "
        f"(the last time: mqtt: query {watch_key!r}: "
    ), err
    # its connection up all along: no reconnection, nothing the transport ended
    assert "connection to the broker lost" not in err, err
