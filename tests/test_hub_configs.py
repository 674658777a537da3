"""The hubs' access control is generated from the trust file; the broker enforces it.

- the shipped router-secure.json5, mosquitto-secure.conf and mosquitto.acl are exactly
  what deploy/make_hub_configs.py makes for the traffic federation, and the same come out
  of a trust file holding those platforms;
- a real mosquitto runs the generated config (TLS on a free port, certificates from
  deploy/make_certs.py): a client without a certificate is refused, a client holding
  uav-a's certificate cannot write uav-b's presence nor read uav-b's ACL inbox;
- client-id takeover (issue 11, item 10): a client connecting with uav-b's configured id
  evicts nobody; one that learnt uav-b's real ids from the broker's log evicts its
  connections, and uav-b reconnects with new ids and keeps serving.
"""

from __future__ import annotations

import asyncio
import os
import pwd
import re
import socket
import ssl
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import paho.mqtt.client as paho
import pytest
from test_membership_auth import WAIT, _federation, _until, node  # noqa: F401

from agents.keys import gen_keys, trust_keys
from agents.transports import free_tcp_port
from federation import FederationPlatform, PlatformConfig

ROOT = Path(__file__).resolve().parent.parent
DEPLOY = ROOT / "deploy"
sys.path.insert(0, str(DEPLOY))
import make_hub_configs  # noqa: E402

pytestmark = pytest.mark.timeout(90)
PLATFORMS = ("uav-a", "uav-b", "uav-c", "operator")


def test_shipped_hub_configs_are_the_generators_output(tmp_path: Path) -> None:
    shipped = {
        "router-secure.json5": make_hub_configs.router_json5("traffic", PLATFORMS),
        "mosquitto-secure.conf": make_hub_configs.mosquitto_conf("traffic", PLATFORMS),
        "mosquitto.acl": make_hub_configs.mosquitto_acl("traffic", PLATFORMS),
    }
    for name, text in shipped.items():
        assert (DEPLOY / "config" / name).read_text() == text, f"regenerate {name}"
    # … and from a trust file of those platforms, by the command a user runs
    pubs = [gen_keys(p, tmp_path / "keys")[2] for p in PLATFORMS]
    trust_keys(tmp_path / "trust.json", pubs, federation="traffic")
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, str(DEPLOY / "make_hub_configs.py"), "--trust-file",
         str(tmp_path / "trust.json"), "--out", str(out)],
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    for name, text in shipped.items():
        assert (out / name).read_text() == text
    # bad input is named, not a traceback
    bad = subprocess.run(
        [sys.executable, str(DEPLOY / "make_hub_configs.py"), "--federation", "traffic",
         "--platform", "uav/a", "--out", str(out)],
        capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert bad.returncode == 1 and "uav/a" in bad.stderr and "Traceback" not in bad.stderr


def _mosquitto(workdir: Path, conf: str) -> Iterator[tuple[int, Path]]:
    exe = "/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else "mosquitto"
    port = free_tcp_port()
    path = workdir / "mosquitto.conf"
    # run as whoever runs the tests (as root mosquitto would switch to user "mosquitto",
    # who cannot read the test's private keys)
    me = pwd.getpwuid(os.getuid()).pw_name
    conf = conf.replace("listener 8883 0.0.0.0", f"user {me}\nlistener {port} 127.0.0.1")
    # the broker's own record of what it denied: a log file, written as it goes
    log = workdir / "mosquitto.log"
    conf = conf.replace("log_dest stdout", f"log_dest file {log}\nlog_type all")
    path.write_text(conf)
    with (workdir / "mosquitto.out").open("wb") as out:
        proc = subprocess.Popen([exe, "-c", str(path)], stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 10
        while True:
            assert proc.poll() is None, (workdir / "mosquitto.out").read_text()
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
                break
            except OSError:
                assert time.monotonic() < deadline, (workdir / "mosquitto.out").read_text()
                time.sleep(0.05)
        yield port, log
    finally:
        proc.kill()
        proc.wait(10)


@pytest.fixture
def tls_broker(tmp_path: Path) -> Iterator[tuple[int, Path]]:
    """The generated broker config with TLS, certificates for uav-a and uav-b."""
    tls = tmp_path / "tls"
    done = subprocess.run(
        [sys.executable, str(DEPLOY / "make_certs.py"), "--dir", str(tls), "--platform=uav-a",
         "--platform=uav-b", "--router-name=127.0.0.1", "--router-name=localhost"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    conf = make_hub_configs.mosquitto_conf("traffic", ["uav-a", "uav-b"])
    (tmp_path / "mosquitto.acl").write_text(
        make_hub_configs.mosquitto_acl("traffic", ["uav-a", "uav-b"])
    )
    conf = conf.replace("/mosquitto/config/tls/", f"{tls}/")
    conf = conf.replace("/mosquitto/config/mosquitto.acl", str(tmp_path / "mosquitto.acl"))
    yield from _mosquitto(tmp_path, conf)


class _Client:
    """A paho client over TLS (with ``cert``'s certificate, or none), recording what it gets."""

    def __init__(self, port: int, tls: Path, cert: str | None) -> None:
        self.got: list[tuple[str, bytes]] = []
        self.connected = threading.Event()
        self.refused: str | None = None
        self.c = paho.Client(paho.CallbackAPIVersion.VERSION2, protocol=paho.MQTTv5)
        ctx = ssl.create_default_context(cafile=str(tls / "ca.crt"))
        if cert is not None:
            ctx.load_cert_chain(str(tls / f"{cert}.crt"), str(tls / f"{cert}.key"))
        self.c.tls_set_context(ctx)
        self.c.on_message = lambda c, u, m: self.got.append((m.topic, m.payload))
        self.c.on_connect = lambda c, u, f, rc, p: (
            self.connected.set() if not rc.is_failure else None
        )
        try:
            self.c.connect("127.0.0.1", port)
        except (ssl.SSLError, OSError) as exc:
            self.refused = str(exc)
            return
        self.c.loop_start()

    def close(self) -> None:
        self.c.loop_stop()
        self.c.disconnect()


def test_the_generated_broker_config_refuses_no_cert_and_fences_identities(
    tls_broker: tuple[int, Path], tmp_path: Path
) -> None:
    port, log = tls_broker
    tls = tmp_path / "tls"
    anonymous = _Client(port, tls, None)
    deadline = time.monotonic() + WAIT
    while "peer did not return a certificate" not in log.read_text():  # the broker's record
        assert time.monotonic() < deadline, log.read_text()
        time.sleep(0.05)
    assert anonymous.refused is not None or not anonymous.connected.is_set()
    if anonymous.refused is None:
        anonymous.close()
    a, b = _Client(port, tls, "uav-a"), _Client(port, tls, "uav-b")
    watcher = _Client(port, tls, "uav-b")
    try:
        for c in (a, b, watcher):
            assert c.connected.wait(WAIT), log.read_text()
        f = "dyknow/traffic/v1"
        watcher.c.subscribe(f"{f}/alive/+", qos=1)
        a.c.subscribe(f"{f}/acl/uav-b", qos=1)  # a spy on uav-b's inbox
        a.c.subscribe(f"{f}/acl/uav-a", qos=1)
        time.sleep(0.5)
        a.c.publish(f"{f}/alive/uav-b", b"", qos=1, retain=True).wait_for_publish(5)
        a.c.publish(f"{f}/alive/uav-b", b'{"v":1,"alive":true}', qos=1).wait_for_publish(5)
        a.c.publish(f"{f}/alive/uav-a", b'{"v":1,"alive":true}', qos=1).wait_for_publish(5)
        b.c.publish(f"{f}/acl/uav-b", b"for uav-b only", qos=1).wait_for_publish(5)
        b.c.publish(f"{f}/acl/uav-a", b"marker", qos=1).wait_for_publish(5)
        deadline = time.monotonic() + WAIT
        while (f"{f}/acl/uav-a", b"marker") not in a.got or not watcher.got:
            assert time.monotonic() < deadline, (a.got, watcher.got)
            time.sleep(0.05)
        time.sleep(0.3)
        assert [t for t, _ in watcher.got] == [f"{f}/alive/uav-a"], watcher.got
        assert (f"{f}/acl/uav-b", b"for uav-b only") not in a.got, a.got
        # the broker's record of the refusals: both of uav-a's writes of uav-b's presence
        denied = re.findall(r"Denied PUBLISH from \S+ \([^'\n]*'([^'\n]+)'", log.read_text())
        assert denied == [f"{f}/alive/uav-b"] * 2, denied
    finally:
        for c in (a, b, watcher):
            c.close()


async def test_a_taken_over_client_id_is_recovered(
    tmp_path: Path,
    node: Callable[[str], subprocess.Popen[str]],  # noqa: F811 (the fixture)
) -> None:
    workdir = tmp_path / "broker"
    workdir.mkdir()
    gen = _mosquitto(
        workdir,
        "listener 8883 0.0.0.0\nallow_anonymous true\npersistence false\nlog_dest stdout\n",
    )
    port, log = next(gen)
    try:
        fed = f"takeover{os.getpid()}"
        mqtt = f'kind = "mqtt"\nhost = "127.0.0.1"\nport = {port}\nkeepalive = 5'
        _federation(
            tmp_path,
            fed,
            ["uav-a", "uav-b"],
            {"uav-a": mqtt, "uav-b": mqtt + '\nclient_id = "dyknow-uav-b"'},
        )
        node("uav-b")
        async with (
            asyncio.timeout(4 * WAIT),
            FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
        ):
            await _until("uav-a sees uav-b", lambda: "uav-b" in a.members)
            ids = set(re.findall(r" as (dyknow-uav-b-[0-9a-f]{16}) ", log.read_text()))
            assert len(ids) >= 2, log.read_text()  # its main connection and its token
            thieves = []
            # the guessable id of old evicts nobody; the real ids, learnt from the log
            for cid in ["dyknow-uav-b", *sorted(ids)]:
                t = paho.Client(
                    paho.CallbackAPIVersion.VERSION2, client_id=cid, protocol=paho.MQTTv5
                )
                t.connect("127.0.0.1", port)
                t.loop_start()
                thieves.append(t)
            await _until(
                "uav-b reconnected with new ids",
                lambda: (
                    len(set(re.findall(r" as (dyknow-uav-b-[0-9a-f]{16}) ", log.read_text())) - ids)
                    >= 2
                ),
            )
            await _until("uav-b is a member again", lambda: "uav-b" in a.members)
            answer = await a.federation_agent.request_from(
                "uav-b", {"action": "list-labels"}, timeout=WAIT
            )
            assert answer is not None
            for t in thieves:
                t.loop_stop()
                t.disconnect()
    finally:
        gen.close()


async def test_platforms_federate_through_the_generated_tls_broker(
    tls_broker: tuple[int, Path], tmp_path: Path
) -> None:
    """The ACL lets the protocol through: membership, key exchange, a request and its answer."""
    port, _ = tls_broker
    tls = tmp_path / "tls"
    names = ["uav-a", "uav-b"]
    transport = {
        n: (
            f'kind = "mqtt"\nhost = "127.0.0.1"\nport = {port}\nclient_id = "dyknow-{n}"\n'
            f'[transport.tls]\nroot_ca_certificate = "{tls}/ca.crt"\n'
            f'certificate = "tls/{n}.crt"\nprivate_key = "tls/{n}.key"'
        )
        for n in names
    }
    _federation(tmp_path, "traffic", names, transport)
    async with (
        asyncio.timeout(4 * WAIT),
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-a.toml")) as a,
        FederationPlatform(PlatformConfig.load(tmp_path / "uav-b.toml")) as b,
    ):
        await _until(
            "uav-a and uav-b see each other", lambda: "uav-b" in a.members and "uav-a" in b.members
        )
        answer = await b.federation_agent.request_from(
            "uav-a", {"action": "list-labels"}, timeout=WAIT
        )
        assert answer == {"labels": []}, answer  # answered (nothing streams there yet)
        assert a.agents.global_df is not None and a.agents.global_df.refused == 0


def test_mqtt_tls_settings_name_what_is_wrong(tmp_path: Path) -> None:
    from pydantic import ValidationError

    from agents import TransportError
    from agents.transports import MqttConfig

    with pytest.raises(ValidationError, match="certificate and private_key"):
        MqttConfig.model_validate(
            {"tls": {"root_ca_certificate": "ca.crt", "certificate": "uav-a.crt"}}
        )
    config = MqttConfig.model_validate({"tls": {"root_ca_certificate": "ca.crt"}})
    assert config.relative_to(tmp_path).tls is not None
    assert config.relative_to(tmp_path).tls.root_ca_certificate == tmp_path / "ca.crt"
    with pytest.raises(TransportError, match=r"tls.root_ca_certificate: .*ca.crt"):
        config.relative_to(tmp_path).tls.context()
