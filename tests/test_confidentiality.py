"""Confidentiality on the wire, attacked from outside: what a listener without a key reads.

Real processes on loopback: ``uav-a`` (a platform streaming a label), the ``operator``
(asking for it, over ACL, and importing it as a stream), the owner's ``dyknow watch`` of
each, and an outsider: a plain zenoh session (no key, no library of ours) in the peer
mesh, subscribed to ``dyknow/<fed>/**``, recording every payload. With the defaults
(``[security] encrypt = true``, ``audit = "sealed"``) the outsider reads no ACL body, no
sample value and no audit record, while the owners' watches show them, decrypted. With
encryption off (debugging) the same capture reads them in clear: the check can fail.

Also attacked: a member sending plain (MAC-only) envelopes to a platform that requires
encryption (refused, counted and audited), and the peer mesh over mutual TLS (a plain
TCP client reaches nobody).
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import struct
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager, contextmanager
from pathlib import Path
from typing import IO, Any

import msgpack
import pytest

from agents import ACLMessage, Performative, wire_key
from agents._security import (
    Handshake,
    KeyPair,
    OwnerBatches,
    SecurityPolicy,
    SessionTable,
    TrustStore,
    watch_request,
)
from agents.keys import gen_keys, trust_keys
from agents.transports import Message, ZenohConfig, ZenohTransport, free_tcp_port

ROOT = Path(__file__).resolve().parent.parent
DEPLOY = ROOT / "deploy"
START = 40.0  # spawned interpreters import zenoh, pydantic and DyKnow: slow when loaded
# The consumer's own budget, from its start, to see the provider listed, agree the stream
# and take its first sample: it ends saying which step ran out, before the test gives up.
CONSUMED = 50.0
BASE = 7777.125  # the provider's samples: BASE, BASE + 1, …
SECRET_LABEL = "uav-a/secret-altitude"  # a local label: only ever inside bodies

NODE = """
import asyncio, sys
from federation import FederationPlatform, PlatformConfig
BASE = float(sys.argv[3])
async def provider(p):
    src = p.instance.add_source(sys.argv[4])
    k = 0
    src.push(BASE)
    print("ready", flush=True)
    while True:
        await asyncio.sleep(0.05)
        k += 1
        src.push(BASE + k)
async def listed(gdf, name):
    came = gdf.watch_presence()
    try:
        while name not in gdf.platforms:
            await anext(came)
    finally:
        came.close()
async def consumer(p):
    within = float(sys.argv[4])
    loop = asyncio.get_running_loop()
    deadline = loop.time() + within
    def left():
        return max(0.1, deadline - loop.time())
    step = "uav-a listed in the directory"
    try:
        gdf = p.agents.global_df
        await asyncio.wait_for(listed(gdf, "uav-a"), left())
        fed = p.federation_agent
        step = "create_stream"
        await fed.create_stream("uav-a", ["heli-altitude"], timeout=left())
        step = "the import"
        label = await p.imported("uav-a", "heli-altitude", timeout=left())
        step = "the first sample"
        sub = p.instance.subscribe(label)
        first = await asyncio.wait_for(anext(aiter(sub)), left())
    except TimeoutError:
        sys.exit(f"consumer: no {step} within {within:g} s of its start")
    print("streaming", first.value, flush=True)
    while True:
        await fed.request_from("uav-a", {"action": "get-latest", "labels": ["heli-altitude"]},
                               timeout=10)
        await asyncio.sleep(0.3)
async def main():
    async with FederationPlatform(PlatformConfig.load(sys.argv[1])) as p:
        await (provider(p) if sys.argv[2] == "provider" else consumer(p))
asyncio.run(main())
"""

OUTSIDER = """
import sys, time, zenoh, msgpack, json
cfg = zenoh.Config()
cfg.insert_json5("mode", json.dumps("peer"))
cfg.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
cfg.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
cfg.insert_json5("scouting/multicast/enabled", "false")
out = open(sys.argv[3], "ab")
def on_sample(s):
    out.write(msgpack.packb([str(s.key_expr), s.payload.to_bytes()]))
    out.flush()
with zenoh.open(cfg) as session:
    session.declare_subscriber(sys.argv[2], on_sample)
    print("listening", flush=True)
    while True:
        time.sleep(1)
"""


def _free_port() -> int:
    # below the ephemeral range: a port from bind(0) may go to another connection first
    return free_tcp_port()


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(ROOT)}


def _write(
    tmp: Path,
    fed: str,
    names: tuple[str, ...],
    transports: dict[str, str],
    security: str = "",
) -> dict[str, Path]:
    """Keys (for every name), trust file, vocabulary, mappings, and a config per transport."""
    pubs = [gen_keys(n, tmp / "keys")[2] for n in names]
    trust_keys(tmp / "trust.json", pubs, federation=fed)
    (tmp / "vocab.toml").write_text('name = "traffic"\n[labels]\n"heli-altitude" = "m"\n')
    configs = {}
    for name, transport in transports.items():
        local = SECRET_LABEL if name == "uav-a" else f"{name}/alt"
        (tmp / f"{name}-labels.toml").write_text(
            f'vocabulary = "traffic"\n[labels]\n"heli-altitude" = "{local}"\n'
        )
        configs[name] = tmp / f"{name}.toml"
        configs[name].write_text(
            f'name = "{name}"\nfederation = "{fed}"\nkey = "keys/{name}.key"\n'
            f'trust = "trust.json"\nvocabulary = "vocab.toml"\nmapping = "{name}-labels.toml"\n'
            f"{security}\n[transport]\n{transport}\n"
        )
    return configs


def _spawn(*args: str, out: bool = True) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, *args],
        stdout=subprocess.PIPE if out else subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env=_env(),
    )


def _line(proc: subprocess.Popen[str], want: str, timeout: float = START) -> str:
    """The first stdout line of ``proc`` starting with ``want``, within ``timeout`` s."""
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout
    import selectors

    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    try:
        while time.monotonic() < deadline:
            if not sel.select(timeout=max(0.0, deadline - time.monotonic())):
                break
            line = proc.stdout.readline()
            if not line:
                break
            if line.startswith(want):
                return line
    finally:
        sel.close()
    # what it said on stderr says why: one still running is stopped to read it
    if proc.poll() is None:
        proc.kill()
    try:
        _, err = proc.communicate(timeout=10)
    except (subprocess.TimeoutExpired, ValueError):  # ValueError: its stdout read already
        err = ""
    raise AssertionError(
        f"no line {want!r} from the process {proc.args[3:]} within {timeout:g} s "
        f"(exit {proc.returncode}): {(err or '')[-3000:]}"
    )


@contextmanager
def _processes() -> Iterator[list[subprocess.Popen[str]]]:
    procs: list[subprocess.Popen[str]] = []
    try:
        yield procs
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait(10)


def _stop(proc: subprocess.Popen[str], timeout: float = 20.0) -> str:
    """SIGINT ``proc`` and return what it printed (it must exit cleanly)."""
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err[-3000:]
    return out


def _follow(proc: subprocess.Popen[str]) -> tuple[list[str], threading.Thread]:
    """The lines ``proc`` prints from now on, gathered as they come (a thread reads them)."""
    lines: list[str] = []

    def read(out: IO[str]) -> None:
        for line in out:
            lines.append(line)

    assert proc.stdout is not None
    reader = threading.Thread(target=read, args=(proc.stdout,), daemon=True)
    reader.start()
    return lines, reader


def _stop_followed(proc: subprocess.Popen[str], lines: list[str], reader: threading.Thread) -> str:
    """`_stop` for a process whose output `_follow` gathers: all it printed since."""
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=20)
    assert proc.stderr is not None
    err = proc.stderr.read()
    assert proc.returncode == 0, err[-3000:]
    reader.join(timeout=20)
    return "".join(lines)


def _owners_saw(a: list[dict[str, Any]], op: list[dict[str, Any]]) -> bool:
    """uav-a's watch and the operator's showed what the test asserts they show, opened."""
    return (
        any(
            e["kind"] == "acl"
            and e["message"].get("sender") == "federation@operator"
            and e["message"]["performative"] == "request"
            for e in a
        )
        and any(e["kind"] == "stream-report" and e["from"] == "operator" for e in a)
        and any(
            e["kind"] == "audit"
            and e["record"]["verdict"] == "accepted"
            and e["record"]["from"] == "operator"
            for e in a
        )
        and any(e["kind"] == "stream" and e["from"] == "uav-a" and e["batch"]["b"] for e in op)
        and any(
            e["kind"] == "acl"
            and e["message"]["performative"] == "inform"
            and "heli-altitude" in json.dumps(e["message"]["content"])
            for e in op
        )
    )


def _claimed_sender(envelope: bytes) -> str:
    """The readable ``from`` of an ACL envelope, JSON or binary (a msgpack array)."""
    if envelope[:1] == b"{":
        return str(json.loads(envelope)["from"])
    return str(msgpack.unpackb(envelope)[1])


def _captured(path: Path) -> list[tuple[str, bytes]]:
    if not path.exists():
        return []
    return [(k, p) for k, p in msgpack.Unpacker(path.open("rb"), raw=False)]


def _events(out: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def _secrets(top: int) -> list[bytes]:
    """How the provider's sample values look in a msgpack batch and in an ACL body (JSON)."""
    values = [BASE + k for k in range(top)]
    return [struct.pack(">d", v) for v in values] + [repr(v).encode() for v in values]


@pytest.mark.timeout(200)
@pytest.mark.parametrize("encrypt", [True, False], ids=["default-encrypted", "encryption-off"])
def test_an_outsider_in_the_peer_mesh_reads_nothing_the_owner_watches_everything(
    tmp_path: Path, encrypt: bool
) -> None:
    """Default: no ACL body, sample or audit record in clear; off: all of them readable."""
    fed = f"conf-{uuid.uuid4().hex[:8]}"
    seed, op_port = _free_port(), _free_port()
    security = "" if encrypt else '[security]\nencrypt = false\naudit = "plain"\n'
    configs = _write(
        tmp_path,
        fed,
        ("uav-a", "operator"),
        {
            "uav-a": f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{seed}"]',
            "operator": (
                f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{op_port}"]\n'
                f'connect = ["tcp/127.0.0.1:{seed}"]'
            ),
        },
        security,
    )
    capture = tmp_path / "outsider.msgpack"
    with _processes() as procs:
        provider = _spawn("-c", NODE, str(configs["uav-a"]), "provider", str(BASE), SECRET_LABEL)
        procs.append(provider)
        _line(provider, "ready")
        outsider = _spawn("-c", OUTSIDER, f"tcp/127.0.0.1:{seed}", f"dyknow/{fed}/**", str(capture))
        procs.append(outsider)
        _line(outsider, "listening")
        watches = {}
        for name in ("uav-a", "operator"):
            cmd = ("-m", "federation.cli", "watch", "--config", str(configs[name]), "--json")
            watches[name] = _spawn(*cmd, "--timeout", str(START))
            procs.append(watches[name])
        _line(watches["uav-a"], '{"kind": "watching"')
        consumer = _spawn(
            "-c", NODE, str(configs["operator"]), "consumer", str(BASE), str(CONSUMED)
        )
        procs.append(consumer)
        _line(consumer, "streaming", START + CONSUMED)
        _line(watches["operator"], '{"kind": "watching"')
        # requests, answers, batches, reports and audit batches flow: until the outsider
        # has captured each kind and each owner's watch has shown what is asserted below
        followed = {name: _follow(w) for name, w in watches.items()}
        deadline = time.monotonic() + START
        while time.monotonic() < deadline:
            kinds = {key.split("/")[3] for key, _ in _captured(capture)}
            a, op = (_events("".join(followed[n][0])) for n in ("uav-a", "operator"))
            if {"acl", "stream", "stream-report", "audit"} <= kinds and _owners_saw(a, op):
                break
            time.sleep(0.1)  # two processes' output and a file: nothing to await here
        seen = {name: _events(_stop_followed(w, *followed[name])) for name, w in watches.items()}
        consumer.kill()
        provider.kill()
        outsider.kill()

    payloads = _captured(capture)
    by_kind: dict[str, list[bytes]] = {}
    for key, payload in payloads:
        kind = key.split("/")[3]
        by_kind.setdefault(kind, []).append(payload)
    # the outsider was in the mesh and saw the traffic: ACL, streams, reports, audit
    for kind in ("acl", "stream", "stream-report", "audit"):
        assert by_kind.get(kind), f"the outsider saw no {kind} payload: {sorted(by_kind)}"
    secrets = _secrets(2000)  # 20 values/s: more than the provider pushed in this test
    readable = [
        (key, s)
        for key, payload in payloads
        for s in (*secrets, b'"performative"', b'"verdict"', SECRET_LABEL.encode())
        if s in payload
    ]
    if encrypt:
        assert not readable, f"in clear on the wire: {readable[:5]}"
        # headers stay visible, as documented: who talks to whom (either envelope form)
        assert "operator" in {_claimed_sender(p) for p in by_kind["acl"]}
    else:
        found = {s for _, s in readable}
        assert b'"performative"' in found and b'"verdict"' in found
        assert any(s in found for s in secrets[: len(secrets) // 2]), "no sample value in clear"

    # the owners see, opened, what reached their platform
    a, op = seen["uav-a"], seen["operator"]
    asked = [
        e for e in a if e["kind"] == "acl" and e["message"].get("sender") == "federation@operator"
    ]
    assert any(m["message"]["performative"] == "request" for m in asked), a[:10]
    assert any(e["kind"] == "stream-report" and e["from"] == "operator" for e in a)
    assert any(
        e["kind"] == "audit"
        and e["record"]["verdict"] == "accepted"
        and e["record"]["from"] == "operator"
        for e in a
    )
    values = [
        s[0] for e in op if e["kind"] == "stream" and e["from"] == "uav-a" for s in e["batch"]["b"]
    ]
    assert values and all(v >= BASE and v == int(v - BASE) + BASE for v in values), op[:10]
    informs = [e for e in op if e["kind"] == "acl" and e["message"]["performative"] == "inform"]
    assert any("heli-altitude" in json.dumps(e["message"]["content"]) for e in informs)


@pytest.mark.timeout(120)
def test_a_plain_envelope_to_a_platform_requiring_encryption_is_refused_counted_audited(
    tmp_path: Path,
) -> None:
    """A member whose sessions do not encrypt: its ACL messages and batches are dropped.

    And an outsider's watch request (signed with a key that is not uav-a's) is refused.
    """
    fed = f"plain-{uuid.uuid4().hex[:8]}"
    seed = _free_port()
    configs = _write(
        tmp_path,
        fed,
        ("uav-a", "uav-m"),
        {"uav-a": f'mode = "peer"\nlisten = ["tcp/127.0.0.1:{seed}"]'},
    )
    with _processes() as procs:
        provider = _spawn("-c", NODE, str(configs["uav-a"]), "provider", str(BASE), SECRET_LABEL)
        procs.append(provider)
        _line(provider, "ready")
        owner = KeyPair.load(tmp_path / "keys" / "uav-a.key")
        records = asyncio.run(_attack_in_plain(tmp_path, fed, seed, owner))

    plain = [r for r in records if str(r["reason"]).startswith("unencrypted:")]
    acl = [r for r in plain if r.get("stage") is None]
    stream = [r for r in plain if r.get("stage") == "stream"]
    # one record per refused envelope: 3 ACL messages and 2 sample batches
    assert len(acl) == 3 and len(stream) == 2, plain
    assert all(r["from"] == "uav-m" and r["verdict"] == "dropped" for r in plain)
    assert "requires encrypted envelopes" in acl[0]["reason"]
    # none of the plain requests was opened and admitted; the encrypted one was
    opened = [r for r in records if r["from"] == "uav-m" and r["performative"] == "request"]
    assert [r["conversation_id"] for r in opened] == ["c-encrypted"], opened
    # the watch request signed with another key than uav-a's: refused and audited
    (watch,) = [r for r in records if r.get("stage") == "watch"]
    assert watch["verdict"] == "dropped" and str(watch["reason"]).startswith("forged:")


@asynccontextmanager
async def _failing_with(records: list[dict[str, Any]]) -> AsyncIterator[None]:
    """A timeout inside says which audit records did arrive."""
    try:
        yield
    except TimeoutError:
        raise AssertionError(f"audit records so far: {records}") from None


async def _attack_in_plain(tmp: Path, fed: str, seed: int, owner: KeyPair) -> list[dict[str, Any]]:
    """As uav-m (a member, our library, MAC-only sessions): send plain, then one encrypted."""
    keys = KeyPair.load(tmp / "keys" / "uav-m.key")
    trust = TrustStore.load(tmp / "trust.json")
    records: list[dict[str, Any]] = []
    batches = OwnerBatches(owner, owner.public_key)

    def opened(item: Message) -> bytes:
        return batches.open(item.key, item.payload)

    async with ZenohTransport(ZenohConfig.loopback(_free_port(), connect=[seed])) as t:
        audit = await t.subscribe(wire_key(fed, "audit", "uav-a"))

        async def session(encrypt: bool) -> SessionTable:
            policy = SecurityPolicy(encrypt=encrypt)
            hs = Handshake(keys, trust, policy=policy)
            table = SessionTable("uav-m", trust, policy=policy)
            async with asyncio.timeout(20):
                while True:
                    kx = wire_key(fed, "kx", "uav-a")
                    replies = await t.query(kx, hs.initiate("uav-a"), timeout=2.0)
                    good = [r for r in replies if r.ok]
                    if good:
                        table.add(hs.finish(good[0].payload))
                        return table
                    hs.cancel("uav-a")
                    await asyncio.sleep(0.2)

        def ask(cid: str) -> bytes:
            return ACLMessage(
                performative=Performative.REQUEST,
                sender="federation@uav-m",
                receivers=["federation@uav-a"],
                content={"action": "get-latest", "labels": ["heli-altitude"]},
                ontology="dyknow-federation",
                conversation_id=cid,
            ).to_json()

        plain = await session(encrypt=False)
        for i in range(3):
            await t.publish(wire_key(fed, "acl", "uav-a"), plain.seal("uav-a", ask(f"c-plain-{i}")))
        batch = msgpack.packb({"v": 1, "s": "heli-altitude", "b": [[1.0, 1, 1]]})
        for _ in range(2):
            await t.publish(
                f"dyknow/{fed}/v1/stream/uav-a/uav-m/heli-altitude",
                plain.seal_bytes("uav-a", batch),
            )
        # an outsider asks to watch uav-a, signing with a key of its own: no answer
        watched = await t.subscribe(wire_key(fed, "watch", "uav-a"))
        impostor = KeyPair.generate("uav-a")
        replies = await t.query(
            wire_key(fed, "watch", "uav-a"), watch_request(impostor, fed), timeout=2.0
        )
        assert not [r for r in replies if r.ok], replies
        encrypted = await session(encrypt=True)
        await t.publish(wire_key(fed, "acl", "uav-a"), encrypted.seal("uav-a", ask("c-encrypted")))

        async with _failing_with(records), asyncio.timeout(30):
            while (
                not any(r["conversation_id"] == "c-encrypted" for r in records)
                or sum(str(r["reason"]).startswith("unencrypted:") for r in records) < 5
                or not any(r.get("stage") == "watch" for r in records)
            ):
                item = await audit.get()
                # the published audit is sealed to uav-a's owner: the test holds its key
                for line in opened(item).splitlines():
                    records.append(json.loads(line))
        await asyncio.sleep(1.0)  # anything more (there must be nothing) would show up here
        while True:
            try:
                item = await audit.get(timeout=0.1)
            except TimeoutError:
                break
            records += [json.loads(x) for x in opened(item).splitlines()]
        assert len(watched.inbox) == 0  # nothing shown to a watcher that did not check out
    return records


# -- the peer mesh over mutual TLS --------------------------------------------------------------

PROBE = """
import json, sys, time, zenoh
settings = json.loads(sys.argv[1])
cfg = zenoh.Config()
cfg.insert_json5("mode", json.dumps("peer"))
cfg.insert_json5("listen/endpoints", json.dumps([]))
cfg.insert_json5("connect/endpoints", json.dumps([settings["connect"]]))
cfg.insert_json5("scouting/multicast/enabled", "false")
for path, value in settings.get("tls", {}).items():
    cfg.insert_json5("transport/link/tls/" + path, json.dumps(value))
got = []
with zenoh.open(cfg) as session:
    session.declare_subscriber(settings["key"], lambda s: got.append(str(s.key_expr)))
    peers = []
    deadline = time.monotonic() + settings["seconds"]
    while time.monotonic() < deadline:
        peers = [str(z) for z in session.info.peers_zid()]
        if settings["until_seen"] and peers and got:
            break  # what it was to show, shown: no need to look on
        time.sleep(0.2)
    print(json.dumps({"peers": peers, "samples": len(got)}), flush=True)
"""


def _make_certs(directory: Path, *platforms: str) -> Path:
    """deploy/make_certs.py, as a user runs it: the federation's CA and platform certificates."""
    args = [sys.executable, str(DEPLOY / "make_certs.py"), "--dir", str(directory)]
    args += [f"--platform={p}" for p in platforms]
    done = subprocess.run(args, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    return directory


def _tls_table(pki: Path, name: str) -> str:
    return (
        f'\n[transport.tls]\nroot_ca_certificate = "{pki / "ca.crt"}"\n'
        f'certificate = "{pki / f"{name}.crt"}"\nprivate_key = "{pki / f"{name}.key"}"\n'
        "verify_name_on_connect = false\n"
    )


def _probes(
    key: str, seconds: float, probes: list[tuple[str, dict[str, Any] | None, bool]]
) -> list[Any]:
    """Plain zenoh sessions, one per (endpoint, TLS settings, until_seen), side by side.

    Each looks ``seconds`` s at whom it reached and what it saw on ``key``; one with
    ``until_seen`` stops as soon as it has a peer and a sample. They run at once: what
    one of them reaches does not depend on the others, and each waits its own ``seconds``
    from its own session's start.
    """
    procs = []
    with _processes() as running:
        for connect, tls, until_seen in probes:
            settings = {
                "connect": connect,
                "key": key,
                "seconds": seconds,
                "tls": tls or {},
                "until_seen": until_seen,
            }
            proc = _spawn("-c", PROBE, json.dumps(settings))
            running.append(proc)
            procs.append(proc)
        results = []
        for proc in procs:
            out, err = proc.communicate(timeout=seconds + START)
            assert proc.returncode == 0, err[-2000:]
            results.append(json.loads(out.strip().splitlines()[-1]))
    return results


@pytest.mark.timeout(180)
def test_peers_over_mutual_tls_federate_and_a_client_without_the_federations_certificate_sees_nothing(  # noqa: E501
    tmp_path: Path,
) -> None:
    """Two platforms on tls/ endpoints (certificates from the federation's CA) federate;
    plain TCP, TLS without a certificate, and a certificate of another CA reach nobody."""
    pki = _make_certs(tmp_path / "tls", "uav-a", "operator")
    rogue = _make_certs(tmp_path / "rogue", "uav-a")
    fed = f"tls-{uuid.uuid4().hex[:8]}"
    seed, op_port = _free_port(), _free_port()
    configs = _write(
        tmp_path,
        fed,
        ("uav-a", "operator"),
        {
            "uav-a": f'mode = "peer"\nlisten = ["tls/127.0.0.1:{seed}"]' + _tls_table(pki, "uav-a"),
            "operator": (
                f'mode = "peer"\nlisten = ["tls/127.0.0.1:{op_port}"]\n'
                f'connect = ["tls/127.0.0.1:{seed}"]' + _tls_table(pki, "operator")
            ),
        },
    )
    with _processes() as procs:
        provider = _spawn("-c", NODE, str(configs["uav-a"]), "provider", str(BASE), SECRET_LABEL)
        procs.append(provider)
        _line(provider, "ready")
        consumer = _spawn(
            "-c", NODE, str(configs["operator"]), "consumer", str(BASE), str(CONSUMED)
        )
        procs.append(consumer)
        # the stream flows between the two, over mutual TLS
        _line(consumer, "streaming", START + CONSUMED)
        # the owner's watch goes over the same TLS links, with the platform's certificate
        cmd = ("-m", "federation.cli", "watch", "--config", str(configs["operator"]), "--json")
        watch = _spawn(*cmd, "--timeout", str(START))
        procs.append(watch)
        _line(watch, '{"kind": "watching"')
        _line(watch, '{"kind": "stream"')
        _stop(watch)

        # TLS, trusting the right CA, but without a client certificate: mTLS refuses it
        anonymous = {"root_ca_certificate": str(pki / "ca.crt"), "verify_name_on_connect": False}
        # a certificate from another CA
        other = {
            **anonymous,
            "connect_certificate": str(rogue / "uav-a.crt"),
            "connect_private_key": str(rogue / "uav-a.key"),
            "enable_mtls": True,
        }
        # the control: the federation's CA and a certificate of it get in (and see traffic)
        member = {
            **anonymous,
            "connect_certificate": str(pki / "operator.crt"),
            "connect_private_key": str(pki / "operator.key"),
            "enable_mtls": True,
        }
        plain, refused, rogue_ca, inside = _probes(
            f"dyknow/{fed}/**",
            3.0,
            [
                (f"tcp/127.0.0.1:{seed}", None, False),  # plain TCP to a TLS listener
                (f"tls/127.0.0.1:{seed}", anonymous, False),
                (f"tls/127.0.0.1:{seed}", other, False),
                (f"tls/127.0.0.1:{seed}", member, True),
            ],
        )
        assert plain == {"peers": [], "samples": 0}, plain  # no session at all
        assert refused["peers"] == [], refused
        assert rogue_ca["peers"] == [], rogue_ca
        assert inside["peers"] and inside["samples"] > 0, inside


def test_watch_prints_one_readable_line_per_event() -> None:
    """``dyknow watch`` without --json: a line per message, batch, report and record."""
    from federation._cli_app import _watch_line
    from federation._cli_net import decode_watched

    acl = ACLMessage(
        performative=Performative.REQUEST,
        sender="federation@operator",
        receivers=["federation@uav-a"],
        content={"action": "get-latest", "labels": ["heli-altitude"]},
        ontology="dyknow-federation",
    ).to_json()
    batch = msgpack.packb({"v": 1, "s": "heli-altitude", "b": [[BASE, 1, 2], [BASE + 1, 3, 4]]})
    report = msgpack.packb({"v": 1, "lost": {"heli-altitude": 0}})
    lines = [
        _watch_line(decode_watched("acl", "operator", 1.0, acl)),
        _watch_line(decode_watched("bin", "uav-b", 1.0, batch)),
        _watch_line(decode_watched("bin", "operator", 1.0, report)),
        _watch_line(
            {"kind": "audit", "record": {"verdict": "dropped", "from": "x", "reason": "r"}}
        ),
        _watch_line(
            {
                "kind": "audit",
                "record": {"verdict": "accepted", "stage": "watch", "reason": "the owner watches"},
            }
        ),
    ]
    assert "request federation@operator -> federation@uav-a [dyknow-federation]" in lines[0]
    assert "get-latest" in lines[0]
    assert f"stream from uav-b heli-altitude: 2 sample(s) {BASE!r}, {BASE + 1!r}" in lines[1]
    assert "report from operator" in lines[2] and "lost" in lines[2]
    assert "audit  dropped from x" in lines[3] and lines[3].endswith(": r")
    assert lines[4].endswith(" audit  accepted (watch): the owner watches")  # no 'from None'
    assert decode_watched("bin", "uav-b", 1.0, b"\xc1")["kind"] == "binary"  # not msgpack


def test_watch_prints_no_dangling_colon_for_an_audit_record_without_reason() -> None:
    """An audit record with an empty or absent reason ends at its head, not at a colon."""
    from federation._cli_app import _watch_line

    for record in (
        {
            "verdict": "accepted",
            "from": "tmc",
            "performative": "request",
            "sender": "federation@tmc",
            "reason": "",
        },
        {
            "verdict": "accepted",
            "from": "tmc",
            "performative": "request",
            "sender": "federation@tmc",
        },
    ):
        line = _watch_line({"kind": "audit", "record": record})
        assert line.endswith(" audit  accepted from tmc request federation@tmc"), line


def test_watch_warns_when_the_platforms_answer_was_not_signed() -> None:
    """A bare answer bounds batches by this side's clock: the text output says so, and how."""
    from federation._cli_app import _watch_line

    signed = _watch_line({"kind": "watching", "platform": "uav-a", "signed": True})
    assert signed == "watching uav-a: messages, batches and audit addressed to it"
    bare = _watch_line(
        {"kind": "watching", "platform": "uav-a", "signed": False, "allowance_s": 30.0}
    ).splitlines()
    assert bare[0] == signed
    assert bare[1].startswith("warning: the platform's answer was not signed")
    assert "this side's clock less the 30 s clock allowance" in bare[1]
