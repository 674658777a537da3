"""An outsider (no key of the federation) against real processes.

Each test starts `dyknow node` processes (`_node_example.Station`) on a federation of
their own, on loopback, and attacks them with the tools an outsider has: a bare zenoh
session in the peer mesh, or a plain paho client on the MQTT broker the platforms use
(a mosquitto of the tests' own). Each asserts what the attack must not achieve.
"""

from __future__ import annotations

import base64
import inspect
import json
import queue
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, TYPE_CHECKING

import msgpack
import orjson
import pytest
import zenoh
from _node_example import Station, _samples

from agents._security import KeyPair, seal_for_owner, sign_owner_batch
from federation._cli_net import _WATCH_MARGIN

if TYPE_CHECKING:
    import paho.mqtt.client as mqtt

pytestmark = pytest.mark.timeout(150)


def _outsider(station: Station) -> zenoh.Session:
    """A plain zenoh client connected to the station's endpoint: no key, no trust file."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{station.port}"]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


def _put(session: zenoh.Session, key: str, payload: bytes) -> None:
    """Publish as the outsider, every message delivered: the tests count what arrives.

    A put drops by default when a queue on its way is full (a burst of 200 kB payloads on
    a loaded machine): the count the watch shows would then depend on the load.
    """
    session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)


def _cli(station: Station, *args: str) -> subprocess.Popen[str]:
    """``dyknow`` with ``args`` in the station's folder, its output piped as text."""
    return station.spawn(*args)


def _watch(station: Station, *args: str) -> subprocess.Popen[str]:
    """The owner's `dyknow watch` of the station with ``args``, once it says it is watching."""
    watch = _cli(station, "watch", "--config", "station-python.toml", *args)
    try:
        assert watch.stdout is not None
        assert "watching" in watch.stdout.readline()
    except BaseException:
        watch.kill()
        watch.communicate()
        raise
    return watch


def _watch_until(
    watch: subprocess.Popen[str], shown: Callable[[list[str]], bool], *, within: float = 40.0
) -> tuple[str, str]:
    """The watch's output once ``shown`` holds for its lines, then interrupted (Ctrl-C).

    Waiting a fixed ``--duration`` for what the attack makes it show cost seconds per test
    and was short on a loaded machine: the lines are awaited (at most ``within`` s), the
    watch must still run then (nothing forged ended it), and it ends as the owner ends it.
    """
    assert watch.stdout is not None
    lines: queue.Queue[str | None] = queue.Queue()

    def read(out: IO[str]) -> None:
        for line in out:
            lines.put(line)
        lines.put(None)

    reader = threading.Thread(target=read, args=(watch.stdout,), daemon=True)
    reader.start()
    seen: list[str] = []
    deadline = time.monotonic() + within
    ended = False
    while not shown(seen):
        try:
            line = lines.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            break
        if line is None:
            ended = True
            break
        seen.append(line)
    if not ended:
        assert watch.poll() is None, "the watch ended before the owner stopped it"
        watch.send_signal(signal.SIGINT)
    watch.wait(timeout=20)
    assert watch.stderr is not None
    err = watch.stderr.read()
    reader.join(timeout=20)
    while not lines.empty():
        if (line := lines.get_nowait()) is not None:
            seen.append(line)
    return "".join(seen), err


def _owner_key(station: Station) -> bytes:
    """The station's public key: in the trust file every member holds, so an outsider's too."""
    trust = json.loads((station.dir / "keys" / "trust.json").read_text())
    return base64.b64decode(trust["platforms"]["station"])


def _stop(
    station: Station, session: zenoh.Session | None, watch: subprocess.Popen[str] | None
) -> None:
    """End the watch if it still runs, the outsider's session and the station."""
    if watch is not None and watch.poll() is None:
        watch.kill()
        watch.communicate()
    if session is not None:
        session.close()
    station.stop()


def test_a_forged_presence_does_not_keep_a_platform_from_starting(tmp_path: Path) -> None:
    """A liveliness token under a member's name, declared by an outsider, is no proof it runs.

    Before, `dyknow node`, `console` and every one-shot command of that member refused
    to start ("platform 'operator' is alive already") for as long as the outsider held
    the token: one token kept a platform out of its federation, or from restarting
    after a crash. Now a presence counts as a running platform only when that platform
    answers a fresh directory query with a statement it signed.
    """
    station = Station(tmp_path)
    session = None
    try:
        station.start("python")
        session = _outsider(station)
        alive = f"dyknow/{station.federation}/v1/alive/operator"
        token = session.liveliness().declare_token(alive)
        # and an answer to "who runs it", as a running node would give
        forged = json.dumps(
            {
                "platform": "operator",
                "federation": station.federation,
                "host": "elsewhere",
                "pid": 1,
                "since": time.time(),
            }
        )
        who = session.declare_queryable(
            f"dyknow/{station.federation}/v1/identity/operator",
            lambda q: q.reply(q.key_expr, forged.encode()),
        )
        seen = list(session.liveliness().get(alive, timeout=2.0))
        assert seen, "the forged token is not routed"
        # a one-shot command as the operator (no node of it runs): not refused
        answer = station.latest("temperature", until=lambda a: bool(_samples(a, "temperature")))
        assert 19.0 <= _samples(answer, "temperature")[0][0] <= 21.0
        # nor the operator's node
        node = _cli(station, "node", "--config", "operator.toml")
        try:
            assert node.stdout is not None
            ready = node.stdout.readline()
            assert f"operator ready in federation {station.federation}" in ready
        finally:
            node.terminate()
            _, err = node.communicate(timeout=20)
        assert "is alive in federation" not in err and "Traceback" not in err
        who.undeclare()
        token.undeclare()
    finally:
        if session is not None:
            session.close()
        _, err = station.stop()
    assert "Traceback" not in err


@pytest.mark.parametrize("as_json", [True, False])
def test_an_outsider_cannot_end_or_feed_the_owners_watch(tmp_path: Path, as_json: bool) -> None:
    """What an outsider publishes on ``audit/<platform>`` and ``watch/<platform>``.

    The owner's `dyknow watch` ended (exit 1, ``JSONDecodeError``, ``TypeError``) on a
    payload that was not the platform's: a plain ``{junk`` on the audit key, a sealed box
    (anyone can seal to the public key) of something other than a list of entries, an
    entry whose fields are not of their types. And it showed a plain audit record as the
    platform's own although the platform seals its audit. Now those show as
    ``unreadable`` and the watch goes on until its owner stops it.
    """
    station = Station(tmp_path)
    session = None
    watch = None
    try:
        station.start("python")
        session = _outsider(station)
        watch = _watch(station, "--duration", "60", *(["--json"] if as_json else []))
        fed = station.federation
        owner = _owner_key(station)
        forged = {"v": 1, "verdict": "accepted", "from": "operator", "reason": "FORGED-PLAIN"}
        deep = b"[" * 100_000 + b"]" * 100_000
        for payload in (orjson.dumps(forged) + b"\n", b"{junk", b"[1]\n"):
            _put(session, f"dyknow/{fed}/v1/audit/station", payload)
        _put(session, f"dyknow/{fed}/v1/audit/station", seal_for_owner(owner, deep))
        for entries in (
            5,
            [["acl"]],
            [["acl", "operator", 1.0, 7]],
            {"a": 1},
            [["acl", "operator", 1e300, b'{"receivers": [1, 2], "sender": {}}']],
            [["bin", "operator", 1.0, msgpack.packb({"s": "x", "b": [1, 2]})]],
            [["acl", "operator", 1.0, deep]],
        ):
            sealed = seal_for_owner(owner, msgpack.packb(entries))
            _put(session, f"dyknow/{fed}/v1/watch/station", sealed)
        # none of the 11 payloads is signed by the platform: each shows as unreadable
        out, err = _watch_until(watch, lambda seen: sum("unreadable" in s for s in seen) >= 11)
    finally:
        _stop(station, session, watch)
    assert watch.returncode == 0, err
    assert "Traceback" not in err and "Error" not in err, err
    assert "FORGED-PLAIN" not in out
    assert out.count("unreadable") >= 7, out


def test_an_outsider_with_the_public_key_cannot_pass_a_batch_off_as_the_platforms(
    tmp_path: Path,
) -> None:
    """Well-formed batches sealed to the owner by an outsider who has the public key only.

    A sealed box is anonymous: before, a list of well-formed entries or audit lines sealed
    to the platform's public key (in the trust file every member holds) showed in `dyknow
    watch` as the platform's own. Now every batch is signed with the platform's key, over
    the key it is published on and its time: the forgeries (unsigned, a random signature,
    an impostor's key, a real batch replayed or moved to the other key) show as
    ``unreadable``, counted, and the platform's own batches verify.
    """
    station = Station(tmp_path)
    session = None
    watch = None
    fed = station.federation
    audit_key, watch_key = f"dyknow/{fed}/v1/audit/station", f"dyknow/{fed}/v1/watch/station"
    try:
        station.start("python")
        session = _outsider(station)
        watch = _watch(station, "--duration", "60", "--json")
        # sealed audit batches the outsider sees go by (the watch sees each one too)
        real: list[bytes] = []
        spy = session.declare_subscriber(audit_key, lambda s: real.append(s.payload.to_bytes()))
        # something for the platform to show: the operator asks it, over the federation
        station.latest("temperature", until=lambda a: bool(_samples(a, "temperature")))
        deadline = time.monotonic() + 10
        while not real and time.monotonic() < deadline:
            time.sleep(0.1)
        assert real, "no audit batch published while the owner watches"
        owner = _owner_key(station)
        impostor = KeyPair.generate("station")
        now = int(time.time() * 1000)
        record = orjson.dumps({"v": 1, "verdict": "accepted", "from": "operator"})
        audit = record[:-1] + b',"reason":"FORGED-AUDIT"}\n'
        body = orjson.dumps({"performative": "inform", "content": "FORGED-WATCH"})
        entries = msgpack.packb([["acl", "operator", time.time(), body]])
        forged = {
            audit_key: [
                seal_for_owner(owner, audit),  # well-formed, unsigned (as before)
                seal_for_owner(owner, bytes(64) + now.to_bytes(8, "big") + audit),
                seal_for_owner(owner, sign_owner_batch(impostor, audit_key, audit, now)),
                real[0],  # the platform's own, replayed
            ],
            watch_key: [
                seal_for_owner(owner, entries),
                seal_for_owner(owner, sign_owner_batch(impostor, watch_key, entries, now)),
                real[0],  # an audit batch moved to the watch key
            ],
        }
        for key, payloads in forged.items():
            for payload in payloads:
                _put(session, key, payload)
        spy.undeclare()

        def shown(seen: list[str]) -> bool:
            events = [json.loads(line) for line in seen]
            refused = sum(e["kind"] == "unreadable" for e in events)
            audits = [e["record"] for e in events if e["kind"] == "audit"]
            acl = [e for e in events if e["kind"] == "acl" and e["from"] == "operator"]
            return refused >= 7 and any(r.get("stage") == "watch" for r in audits) and bool(acl)

        out, err = _watch_until(watch, shown)
    finally:
        _stop(station, session, watch)
    assert watch.returncode == 0, err
    assert "Traceback" not in err, err
    assert "FORGED" not in out
    events = [json.loads(line) for line in out.splitlines()]
    refused = [e for e in events if e["kind"] == "unreadable"]
    assert len(refused) == 7, refused
    assert [e["count"] for e in refused] == list(range(1, 8))
    assert any("seen before" in e["error"] for e in refused), refused  # the replay
    # the platform's own batches verify: its audit, and what reached it from the operator
    assert any(e["kind"] == "audit" and e["record"].get("stage") == "watch" for e in events)
    assert any(e["kind"] == "acl" and e["from"] == "operator" for e in events), events


def test_the_owners_watch_refuses_a_batch_recorded_before_it_began(tmp_path: Path) -> None:
    """An outsider records the platform's sealed audit batches (its subscriber is reason
    enough for the platform to publish them), then replays them to an owner's watch begun
    since, within the 30 s skew. The watch never saw them go by, so its memory of the
    signatures it accepted could not catch them: before, they showed as the platform's
    current audit. Now a batch signed before the watch began is ``unreadable``, counted,
    and the platform's own batches since still verify.
    """
    station = Station(tmp_path)
    session = None
    watch = None
    audit_key = f"dyknow/{station.federation}/v1/audit/station"
    try:
        station.start("python")
        session = _outsider(station)
        recorded: list[bytes] = []
        heard = threading.Event()

        def record(sample: zenoh.Sample) -> None:
            recorded.append(sample.payload.to_bytes())
            heard.set()

        spy = session.declare_subscriber(audit_key, record)
        # something for the platform to audit: the operator asks it, over the federation
        station.latest("temperature", until=lambda a: bool(_samples(a, "temperature")))
        assert heard.wait(20), "no audit batch published while the outsider listened"
        spy.undeclare()
        # the watch's bound allows a batch signed just before it began listening: the
        # replayed ones are older than that, as a recording always is by the replay
        heard_at = time.monotonic()
        replayed = recorded[:5]
        time.sleep(max(0.0, heard_at + 4 * _WATCH_MARGIN - time.monotonic()))
        watch = _watch(station, "--duration", "60", "--json")
        for payload in replayed:
            _put(session, audit_key, payload)

        def shown(seen: list[str]) -> bool:
            events = [json.loads(line) for line in seen]
            refused = sum(e["kind"] == "unreadable" for e in events)
            audits = [e["record"] for e in events if e["kind"] == "audit"]
            return refused >= len(replayed) and any(r.get("stage") == "watch" for r in audits)

        out, err = _watch_until(watch, shown)
    finally:
        _stop(station, session, watch)
    assert watch.returncode == 0, err
    assert "Traceback" not in err, err
    events = [json.loads(line) for line in out.splitlines()]
    refused = [e for e in events if e["kind"] == "unreadable"]
    assert [e["count"] for e in refused] == list(range(1, len(replayed) + 1)), (out, err)
    assert all("before this side began reading" in e["error"] for e in refused), refused
    assert all(e["key"] == audit_key for e in refused), refused
    # the platform's own batches since verify: the audit of the watch request it took
    assert any(e["kind"] == "audit" and e["record"].get("stage") == "watch" for e in events)


def _over_mqtt(station: Station, port: int) -> None:
    """The station's and the operator's configs with the MQTT transport on ``port``."""
    for name, client in (("station-python.toml", "station"), ("operator.toml", "operator")):
        conf = station.dir / name
        text = conf.read_text()
        start = text.index("[transport]")
        end = text.find("\n[", start)
        rest = text[end:] if end != -1 else ""
        transport = (
            f'[transport]\nkind = "mqtt"\nhost = "127.0.0.1"\nport = {port}\n'
            f'client_id = "{client}"\n'
        )
        conf.write_text(text[:start] + transport + rest)


def test_one_mqtt_message_does_not_make_a_platform_deaf(
    tmp_path: Path, mosquitto: tuple[str, int]
) -> None:
    """An outsider on the broker (a plain paho client, no key) against an MQTT node.

    Before, one message ended the transport's receive task: the node ran on but
    received nothing more (no key exchange answered, no request, no batch): a message on
    the platform's ``acl`` key with a user property ``att`` that is not base64
    (``binascii.Error``), or a query whose ``key`` has thousands of ``**`` chunks
    (``RecursionError`` in the key matching, which took exponential time on fewer), or
    a presence nested too deep for the JSON parser (``RecursionError`` again).
    Now such a message is dropped and the platform answers as before.
    """
    import paho.mqtt.client as mqtt
    from paho.mqtt.packettypes import PacketTypes
    from paho.mqtt.properties import Properties

    host, port = mosquitto
    station = Station(tmp_path)
    _over_mqtt(station, port)
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, protocol=mqtt.MQTTv5)
    try:
        station.start("python")
        station.latest("temperature", until=lambda a: bool(_samples(a, "temperature")))
        client.connect(host, port)
        client.loop_start()
        fed = station.federation
        bad_att = Properties(PacketTypes.PUBLISH)
        bad_att.UserProperty = [("att", "!!not base64")]
        client.publish(f"dyknow/{fed}/v1/acl/station", b"x", properties=bad_att).wait_for_publish()
        deep_json = b"[" * 100_000 + b"]" * 100_000  # RecursionError in the presence watcher
        client.publish(f"dyknow/{fed}/v1/alive/operator", deep_json).wait_for_publish()
        for chunks in (["**"] * 3000, ["**", "*"] * 40):
            deep = Properties(PacketTypes.PUBLISH)
            deep.UserProperty = [("key", "/".join([*chunks, "nowhere"]))]
            deep.ResponseTopic = "@reply/outsider/1"
            deep.CorrelationData = b"1"
            client.publish("@query/dyknow", b"x", properties=deep).wait_for_publish()
        wild = Properties(PacketTypes.PUBLISH)  # an answer to no topic: the handler failed
        wild.UserProperty = [("key", f"dyknow/{fed}/v1/identity/station")]
        wild.ResponseTopic = "@reply/+/x"
        client.publish(f"@query/dyknow/{fed}/v1/identity", b"", properties=wild).wait_for_publish()
        time.sleep(1.0)
        # a new one-shot command: a new key exchange, a request and its answer
        answer = station.latest("temperature", until=lambda a: bool(_samples(a, "temperature")))
        assert 19.0 <= _samples(answer, "temperature")[0][0] <= 21.0
    finally:
        client.loop_stop()
        client.disconnect()
        _, err = station.stop()
    assert "receive failed" not in err and "dropping a message" not in err, err
    assert "Publish topic cannot contain wildcards" not in err, err


def _rss_mb(pid: int) -> int:
    """A process's resident memory, in MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) // 1024
    raise AssertionError(f"no VmRSS for pid {pid}")


def _read_up_to_here(
    station: Station, client: mqtt.Client, tag: str, *, within: float = 90.0
) -> None:
    """Wait until the node has read every message ``client`` published on the broker so far.

    RSS read while the node still reads its backlog counts the backlog: on a loaded
    machine a node starved of CPU moves slowly enough to look settled meanwhile. A
    malformed presence published now (on a key of its own) is warned of on the node's
    stderr as its transport reads it, after all that came before (the broker keeps one
    client's order). The broker may drop it as it drops the flood's: one more each
    second, until the node tells of any.
    """
    deadline = time.monotonic() + within
    n = 0
    while (left := deadline - time.monotonic()) > 0:
        client.publish(f"dyknow/{station.federation}/v1/alive/read-{tag}-{n}", b"{", qos=0)
        if station.said(f"/alive/read-{tag}-", within=min(1.0, left)):
            return
        n += 1
    raise AssertionError(f"the node read nothing more of the broker's within {within:g} s")


def _settled_rss_mb(pid: int, *, within: float = 90.0) -> int:
    """A process's resident memory once it stops moving, in MiB (its backlog read first).

    What the node read is still being taken by its watchers (their inboxes, bounded):
    settled is three readings 0.5 s apart within 1 MiB of each other (at most ``within``
    s, then the last reading).
    """
    readings = [_rss_mb(pid)]
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        time.sleep(0.5)
        readings.append(_rss_mb(pid))
        if len(readings) >= 3 and max(readings[-3:]) - min(readings[-3:]) <= 1:
            break
    return readings[-1]


def _presence_allowed_mib(key_length: int) -> float:
    """What an MQTT platform's presence watchers may hold of a flood's keys, in MiB.

    Two watchers (the Interface Agent's, the directory's), each with its inbox of
    changes not yet taken (``watch_presence``'s ``buffer_size``: a change holds its key)
    and the keys it remembers (`_MAX_PRESENCE_KEYS`, of at most `_MAX_PRESENCE_KEY`
    characters); ~200 bytes more per entry for the objects and the dict's slot.
    """
    from agents.transports import MqttTransport
    from agents.transports._mqtt import _MAX_PRESENCE_KEY, _MAX_PRESENCE_KEYS

    inbox = inspect.signature(MqttTransport.watch_presence).parameters["buffer_size"].default
    per_watcher = inbox * (key_length + 200) + _MAX_PRESENCE_KEYS * (_MAX_PRESENCE_KEY + 200)
    return 2 * per_watcher / 2**20


def test_presences_under_invented_names_cost_an_mqtt_platform_bounded_memory(
    tmp_path: Path, mosquitto: tuple[str, int]
) -> None:
    """An outsider publishing presences under ever new keys on the broker.

    Every presence watcher of the platform (its Interface Agent's, its directory's)
    remembered every key it ever heard, for good: ~35-50 MiB more per 10 000 keys of 8 kB,
    without end. Now what it remembers is bounded; the platform still answers.

    The bound on the growth is what the watchers may hold (`_presence_allowed_mib`), from
    one reading to the next, plus the allocator's margin; the flood between the two
    readings compared (50 000 keys) is long enough that unbounded watchers exceed it 2
    times over (tried, the watchers' bound removed: 198 MiB against a bound of 98; with
    it, 8 to 34 MiB).
    """
    import paho.mqtt.client as mqtt

    host, port = mosquitto
    station = Station(tmp_path)
    _over_mqtt(station, port)
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, protocol=mqtt.MQTTv5)
    long = "x" * 8000
    phases, per_phase = 7, 10_000
    allowed = _presence_allowed_mib(len(f"dyknow/{station.federation}/v1/alive/{long}0-0"))
    # glibc's malloc keeps freed blocks for reuse rather than return them; new 8 kB keys
    # in blocks freed by others fragment it (measured: up to ~20 MiB once the first
    # phases have filled what is bounded)
    bound = allowed + 24
    try:
        station.start("python")
        station.follow_stderr()
        node = station.node
        assert node is not None
        client.connect(host, port)
        client.loop_start()
        rss = []
        for phase in range(phases):
            for i in range(per_phase):
                key = f"dyknow/{station.federation}/v1/alive/{long}{phase}-{i}"
                client.publish(key, b'{"v":1,"alive":true}', qos=0)
                if i % 1000 == 0:
                    time.sleep(0.05)  # paced: the broker drops what a slow reader cannot take
            _read_up_to_here(station, client, str(phase))
            rss.append(_settled_rss_mb(node.pid))
        print(f"\nthe platform's RSS after each phase (MiB): {rss}, bound on growth {bound:.0f}")
        # the first phases fill what is bounded (and the allocator's arenas); then what
        # it may hold at most, whatever more comes
        assert rss[-1] - rss[1] < bound, rss
        answer = station.latest("temperature", until=lambda a: bool(_samples(a, "temperature")))
        assert 19.0 <= _samples(answer, "temperature")[0][0] <= 21.0
    finally:
        client.loop_stop()
        client.disconnect()
        _, err = station.stop()
    assert "receive failed" not in err, err


def test_no_answer_to_the_owners_watch_query_ends_the_watch(tmp_path: Path) -> None:
    """An outsider's queryable answers each watch request with junk of every shape.

    Before, a signed-looking answer with a negative ``ts_ms`` ended `dyknow watch`
    (exit 1, "int too large to convert": the time was packed into the transcript before
    it was checked). Now each answer that is not the platform's, whatever its bytes, is
    refused, shown as ``unreadable`` and counted; the watch stays up, bounded by the
    platform's own signed answer, and goes on showing the platform's batches.
    """
    station = Station(tmp_path)
    session = None
    watch = None
    watch_key = f"dyknow/{station.federation}/v1/watch/station"
    zero_sig = base64.b64encode(bytes(64)).decode()
    signed = {"v": 1, "watching": True, "lease_s": 10.0, "ts_ms": 1, "sig": zero_sig}
    variants: list[dict[str, object]] = [
        {"ts_ms": -1},
        {"ts_ms": 2**63},
        {"ts_ms": 2**64 + 1},
        {"ts_ms": 1.5},
        {"ts_ms": True},
        {"ts_ms": "1"},
        {"sig": "!!not base64!!"},
        {"sig": zero_sig.rstrip("=")},
        {"sig": zero_sig[:-4] + "AAA="},  # padding bits set: not canonical
        {"lease_s": -1},
        {"lease_s": "10"},
        {"v": 2},
        {"v": True},
        {"extra": 1},
        {"pad": "x" * 5000},
        {},  # well-formed, a signature of zeros
    ]
    junk = [json.dumps(signed | v).encode() for v in variants]
    junk.append(b"[" * 5000)
    try:
        station.start("python")
        session = _outsider(station)
        watch = _cli(
            station, "watch", "--config", "station-python.toml", "--duration", "60", "--json"
        )
        assert watch.stdout is not None
        first = json.loads(watch.stdout.readline())

        def answer(query: zenoh.Query) -> None:
            for payload in junk:
                query.reply(watch_key, payload)

        queryable = session.declare_queryable(watch_key, answer)

        def shown(seen: list[str]) -> bool:
            events = [json.loads(line) for line in seen]
            refused = [i for i, e in enumerate(events) if e["kind"] == "unreadable"]
            later = [
                i
                for i, e in enumerate(events)
                if e["kind"] == "audit" and e["record"].get("stage") == "watch"
            ]
            # two renewals' junk, and a batch of the platform's shown after the first
            return len(refused) >= 2 * len(junk) and bool(later) and later[-1] > refused[0]

        out, err = _watch_until(watch, shown)
        queryable.undeclare()
    finally:
        _stop(station, session, watch)
    assert watch.returncode == 0, err
    assert "Traceback" not in err and "int too large" not in err, err
    events = [json.loads(line) for line in out.splitlines()]
    refused = [e for e in events if e["kind"] == "unreadable"]
    assert [e["count"] for e in refused] == list(range(1, len(refused) + 1))
    assert all(e["error"].startswith("watch answer refused: ") for e in refused), refused
    assert all(e["key"] == watch_key for e in refused), refused
    # the junk never loosened the bound: the platform's own answer was signed
    assert first == {"kind": "watching", "platform": "station", "signed": True}, first
    assert not [e for e in events if e["kind"] == "watching"], out


def test_a_bare_answer_to_the_owners_watch_is_shown_with_the_bound_it_leaves(
    tmp_path: Path,
) -> None:
    """An outsider answers the watch query bare, as a platform of an older release would.

    Before, the watch took it silently: its batches' bound fell back to this side's clock
    less the 30 s allowance, and nothing said so. Now the first line says the answer was
    not signed, and the text output warns, naming the fallback bound. (The platform here
    does not serve the watch, so the bare answer is the only one.)
    """
    station = Station(tmp_path)
    unwatched = (station.dir / "station-python.toml").read_text() + "\n[security]\nwatch = false\n"
    (station.dir / "station-unwatched.toml").write_text(unwatched)
    session = None
    watches: list[subprocess.Popen[str]] = []
    watch_key = f"dyknow/{station.federation}/v1/watch/station"
    try:
        station.start("unwatched")
        session = _outsider(station)
        queryable = session.declare_queryable(
            watch_key,
            lambda q: q.reply(watch_key, b'{"v":1,"watching":true,"lease_s":10.0}'),
        )
        for args in (["--json"], []):
            watches.append(
                _cli(station, "watch", "--config", "station-python.toml", "--duration", "60", *args)
            )
        as_json, as_text = watches
        assert as_json.stdout is not None and as_text.stdout is not None
        first = json.loads(as_json.stdout.readline())
        head = [as_text.stdout.readline(), as_text.stdout.readline()]
        assert all(w.poll() is None for w in watches), "a watch ended on a bare answer"
        queryable.undeclare()
    finally:
        for w in watches:
            if w.poll() is None:
                w.send_signal(signal.SIGINT)
            w.communicate(timeout=20)
        if session is not None:
            session.close()
        station.stop()
    assert first == {
        "kind": "watching",
        "platform": "station",
        "signed": False,
        "allowance_s": 30.0,
    }
    assert head[0].startswith("watching station:"), head
    assert head[1].startswith("warning: the platform's answer was not signed"), head
    assert "this side's clock less the 30 s clock allowance" in head[1], head
    assert [w.returncode for w in watches] == [0, 0]
