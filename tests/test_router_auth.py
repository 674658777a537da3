"""The authenticated router (deploy/config/router-secure.json5) keeps out and fences in.

One ``dyknow router`` process runs the shipped config (its /etc/dyknow/tls/ paths pointed
at certificates deploy/make_certs.py makes in a temporary directory) on a free loopback
port. Against it:

1. clients without a certificate, with a certificate from another CA, with a wrong or
   no password cannot open a session at all;
2. uav-a and uav-b, as real federation platforms configured by deploy/config/secure/*.toml,
   find each other, answer a get-latest and stream samples through it;
3. uav-a's puts and liveliness tokens under uav-b's keys never reach a subscriber, nor can
   uav-a subscribe to what is addressed to uav-b, while its own keys go through.

"Never reach" is proven without sleeping: after each denied message uav-a sends an
allowed one on the same link, and links keep order, so once the allowed one arrived the
denied one would have arrived before it.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import select
import subprocess
import sys
import time
import tomllib
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from agents import TransportError
from agents.keys import gen_keys, trust_keys
from agents.transports import Message, Presence, Subscription, ZenohTransport, free_tcp_port
from agents.transports._zenoh import ZenohConfig, ZenohTls, ZenohUser
from federation import FederationPlatform, PlatformConfig, PlatformConfigError

ROOT = Path(__file__).resolve().parent.parent
DEPLOY = ROOT / "deploy"
FED = "dyknow/traffic/v1"
DYKNOW = (sys.executable, "-m", "federation.cli")
MAKE_CERTS = (sys.executable, str(DEPLOY / "make_certs.py"))
WAIT = 10.0  # the bound on any single wait
PROBE = b"probe"
MARK = b"uav-a's own"

pytestmark = pytest.mark.timeout(60)


def _free_port() -> int:
    # below the ephemeral range: a port from bind(0) may go to another connection first
    return free_tcp_port()


def _make_certs(directory: Path, *platforms: str) -> Path:
    """Run deploy/make_certs.py, as a user would, for a router on loopback."""
    args = [*MAKE_CERTS, "--dir", str(directory)]
    args += [f"--platform={p}" for p in platforms]
    args += ["--router-name=localhost", "--router-name=127.0.0.1"]
    done = subprocess.run(args, capture_output=True, text=True, timeout=30, check=False)
    assert done.returncode == 0, done.stderr
    return directory


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The federation's certificates and passwords, and another CA's for uav-a."""
    base = tmp_path_factory.mktemp("pki")
    return {
        "tls": _make_certs(base / "tls", "uav-a", "uav-b"),
        "rogue": _make_certs(base / "rogue", "uav-a"),
    }


_ROUTER_FILES = (
    "transport/link/tls/listen_certificate",
    "transport/link/tls/listen_private_key",
    "transport/link/tls/root_ca_certificate",
    "transport/auth/usrpwd/dictionary_file",
)


@pytest.fixture(scope="module")
def router(pki: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``dyknow router`` with the shipped secure config; yields its TLS endpoint."""
    tmp = tmp_path_factory.mktemp("router")
    text = (DEPLOY / "config" / "router-secure.json5").read_text()
    config = tmp / "router-secure.json5"
    config.write_text(text.replace("/etc/dyknow/tls/", f"{pki['tls']}/"))
    parsed = zenoh.Config.from_json5(config.read_text())
    for path in _ROUTER_FILES:  # every file the router reads now is one make_certs.py made
        assert Path(json.loads(parsed.get_json(path))).parent == pki["tls"], path
    endpoint = f"tls/127.0.0.1:{_free_port()}"
    stderr = (tmp / "router.err").open("w")
    proc = subprocess.Popen(
        [*DYKNOW, "router", "--zenoh-config", str(config), "--listen", endpoint],
        stdout=subprocess.PIPE,
        stderr=stderr,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], WAIT)
        line = proc.stdout.readline() if ready else ""
        assert "dyknow router: zid" in line, (tmp / "router.err").read_text()
        print(f"router: {line.strip()}")
        yield endpoint
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        if proc.stdout is not None:
            proc.stdout.close()
        stderr.close()


def _client(
    endpoint: str,
    ca: Path,
    cert: tuple[Path, Path] | None,
    user: str | None = None,
    password_file: Path | None = None,
) -> ZenohTransport:
    """A zenoh client of the router with the given credentials (None: left out)."""
    tls = ZenohTls(
        root_ca_certificate=ca,
        certificate=None if cert is None else cert[0],
        private_key=None if cert is None else cert[1],
    )
    usrpwd = (
        None
        if user is None or password_file is None
        else ZenohUser(user=user, password_file=password_file)
    )
    return ZenohTransport(ZenohConfig(mode="client", connect=(endpoint,), tls=tls, usrpwd=usrpwd))


def _platform(endpoint: str, pki: Path, name: str, password: str | None = None) -> ZenohTransport:
    """``name``'s own credentials (or its certificate with another password)."""
    pw_file = pki / f"{name}.password"
    if password is not None:
        pw_file = pki / f"{name}.wrong-password"
        pw_file.write_text(password + "\n")
    cert = (pki / f"{name}.crt", pki / f"{name}.key")
    return _client(endpoint, pki / "ca.crt", cert, name, pw_file)


# -- 1. who cannot connect ----------------------------------------------------------------


async def test_clients_without_the_federations_certificate_or_password_cannot_connect(
    router: str, pki: dict[str, Path]
) -> None:
    tls, rogue = pki["tls"], pki["rogue"]
    guess = tls / "mallory.password"
    guess.write_text((tls / "uav-a.password").read_text())
    refused = {
        "no client certificate": _client(
            router, tls / "ca.crt", None, "uav-a", tls / "uav-a.password"
        ),
        "a certificate from another CA": _client(
            router,
            tls / "ca.crt",
            (rogue / "uav-a.crt", rogue / "uav-a.key"),
            "uav-a",
            tls / "uav-a.password",
        ),
        "a router certificate from another CA": _client(
            router,
            rogue / "ca.crt",
            (rogue / "uav-a.crt", rogue / "uav-a.key"),
            "uav-a",
            rogue / "uav-a.password",
        ),
        "a wrong password": _platform(router, tls, "uav-a", password="not-the-password"),
        "no user/password": _client(router, tls / "ca.crt", (tls / "uav-a.crt", tls / "uav-a.key")),
        "a user the router does not know": _client(
            router, tls / "ca.crt", (tls / "uav-a.crt", tls / "uav-a.key"), "mallory", guess
        ),
    }
    for what, transport in refused.items():
        with pytest.raises(TransportError, match="cannot open a session"):
            async with asyncio.timeout(WAIT), transport:
                pass
        print(f"refused: {what}")
    # the same router admits the right certificate and password (the refusals are real)
    async with asyncio.timeout(WAIT), _platform(router, tls, "uav-a"):
        print("admitted: uav-a with its certificate and password")


# -- 2. what the federation needs goes through ----------------------------------------------


def _secure_config(tmp: Path, name: str, endpoint: str, pki: Path) -> PlatformConfig:
    """deploy/config/secure/<name>.toml, its /etc/dyknow/tls/ and router address made local."""
    data: dict[str, Any] = tomllib.loads(
        (DEPLOY / "config" / "secure" / f"{name}.toml").read_text()
    )
    transport = data["transport"]
    assert transport["connect"] == ["tls/172.28.0.10:7447"]
    transport["connect"] = [endpoint]
    for table in ("tls", "usrpwd"):
        for field, value in transport[table].items():
            if isinstance(value, str) and value.startswith("/etc/dyknow/tls/"):
                transport[table][field] = str(pki / value.removeprefix("/etc/dyknow/tls/"))
    return PlatformConfig.from_dict(data, source=f"secure/{name}.toml").relative_to(tmp / "secure")


async def test_two_platforms_federate_through_the_authenticated_router(
    router: str, pki: dict[str, Path], tmp_path: Path
) -> None:
    # the layout of deploy/config: keys/, the vocabulary and mappings next to secure/
    pubs = [gen_keys(name, tmp_path / "keys")[2] for name in ("uav-a", "uav-b")]
    trust_keys(tmp_path / "keys" / "trust.json", pubs, federation="traffic")
    for name in ("traffic.toml", "uav-a-labels.toml", "uav-b-labels.toml"):
        (tmp_path / name).write_text((DEPLOY / "config" / name).read_text())
    (tmp_path / "secure").mkdir()
    configs = {n: _secure_config(tmp_path, n, router, pki["tls"]) for n in ("uav-a", "uav-b")}
    started = time.monotonic()
    async with contextlib.AsyncExitStack() as stack, asyncio.timeout(2 * WAIT):
        a = await stack.enter_async_context(FederationPlatform(configs["uav-a"]))
        b = await stack.enter_async_context(FederationPlatform(configs["uav-b"]))
        position = a.instance.add_source("uav/self/position")
        position.push({"x": 1.0, "y": 2.0, "z": 30.0})
        async with b.membership() as events:
            while "uav-a" not in b.members:
                await events.get()
        print(f"uav-b sees uav-a after {time.monotonic() - started:.2f} s")
        answer = await b.federation_agent.request_from(
            "uav-a", {"action": "get-latest", "labels": ["heli-position"]}, timeout=WAIT
        )
        samples = answer["heli-position"]["samples"]
        assert [s[0] for s in samples] == [{"x": 1.0, "y": 2.0, "z": 30.0}]
        print("get-latest heli-position from uav-a answered through the router")
        # a stream: samples on stream/uav-b/uav-a/heli-position, uav-a's own key
        await b.federation_agent.create_stream("uav-a", ["heli-position"], timeout=WAIT)
        # the export sends what is pushed from now on
        position.push({"x": 5.0, "y": 2.0, "z": 30.0})
        label = await b.imported("uav-a", "heli-position", timeout=WAIT)
        assert b.instance.latest(label).samples[0].value == {"x": 5.0, "y": 2.0, "z": 30.0}
        print(f"stream heli-position uav-a -> uav-b flows ({time.monotonic() - started:.2f} s)")


# -- 3. a platform publishes only under its own keys -----------------------------------------


@contextlib.asynccontextmanager
async def _opened(*transports: ZenohTransport) -> AsyncIterator[None]:
    async with contextlib.AsyncExitStack() as stack:
        async with asyncio.timeout(WAIT):
            for t in transports:
                await stack.enter_async_context(t)
        yield


async def _keys_until(
    sub: Subscription[Message], marker: tuple[str, bytes], pub: ZenohTransport
) -> list[str]:
    """The keys received until ``marker`` (key, payload), which ``pub`` puts, arrives;
    probes left out (bounded)."""
    keys: list[str] = []
    async with asyncio.timeout(WAIT):
        await pub.publish(*marker)
        while True:
            try:
                message = await sub.get(timeout=0.5)
            except TimeoutError:  # a put may be dropped on a busy machine (congestion): again
                await pub.publish(*marker)
                continue
            if (message.key, message.payload) == marker:
                return keys
            if message.payload != PROBE:
                keys.append(message.key)


async def _reachable(pub: ZenohTransport, sub: Subscription[Message], key: str) -> None:
    """Put probes on ``key`` until the subscription sees one: the router knows the subscriber."""
    async with asyncio.timeout(WAIT):
        while True:
            await pub.publish(key, PROBE)
            with contextlib.suppress(TimeoutError):
                if (await sub.get(timeout=0.1)).key == key:
                    return


async def test_a_platform_cannot_publish_or_subscribe_under_another_platforms_keys(
    router: str, pki: dict[str, Path]
) -> None:
    tls = pki["tls"]
    a, b = _platform(router, tls, "uav-a"), _platform(router, tls, "uav-b")
    async with _opened(a, b):
        # what uav-b (or anyone) may watch, each with uav-a's forgeries and its own key
        cases = {
            f"{FED}/stream/uav-b/**": (
                [f"{FED}/stream/uav-b/uav-b/heli-position", f"{FED}/stream/uav-b/uav-c/x"],
                f"{FED}/stream/uav-b/uav-a/heli-position",
            ),
            f"{FED}/stream-report/uav-b/*": (
                [f"{FED}/stream-report/uav-b/uav-c"],
                f"{FED}/stream-report/uav-b/uav-a",
            ),
            f"{FED}/df-events/*": ([f"{FED}/df-events/uav-b"], f"{FED}/df-events/uav-a"),
            f"{FED}/audit/*": ([f"{FED}/audit/uav-b"], f"{FED}/audit/uav-a"),
        }
        for key_expr, (forged, own) in cases.items():
            for key in forged:  # publishers first: they then hear of the subscriber in time
                await a.publish(key, PROBE)
            sub = await b.subscribe(key_expr)
            await _reachable(a, sub, own)
            for key in forged:
                await a.publish(key, b"forged by uav-a")
            assert await _keys_until(sub, (own, MARK), a) == [], key_expr
            sub.close()
            print(f"denied: uav-a put on {', '.join(forged)}; allowed: {own}")

        # presence: a token for uav-b declared by uav-a is never seen. Once uav-b sees
        # uav-a's own token, uav-a declares the forged one and then drops its own: had the
        # forged one been let through, it would be seen before its own token's end.
        own, forged_key = f"{FED}/alive/uav-a", f"{FED}/alive/uav-b"
        watch: Subscription[Presence] = await b.watch_presence(f"{FED}/alive/*", history=False)
        seen: list[Presence] = []
        async with asyncio.timeout(WAIT):
            token = await a.declare_token(own)
            while Presence(own, True) not in seen:
                try:
                    seen.append(await watch.get(timeout=0.2))
                except TimeoutError:  # declared before the router knew the watcher: again
                    token.close()
                    token = await a.declare_token(own)
            forged_token = await a.declare_token(forged_key)
            token.close()
            while Presence(own, False) not in seen:
                seen.append(await watch.get())
        assert Presence(forged_key, True) not in seen, seen
        forged_token.close()
        watch.close()
        print("denied: uav-a's liveliness token alive/uav-b; allowed: alive/uav-a")

        # reading uav-b's ACL inbox: uav-a's subscription is refused by the router, so
        # what uav-b is sent never reaches uav-a (uav-b's next message to uav-a does)
        # (uav-b's publisher exists first: it then hears of subscribers as they come, in
        # the router's order, so once it reaches uav-a's inbox it knows of the spy too)
        await b.publish(f"{FED}/acl/uav-b", PROBE)
        spy = await a.subscribe(f"{FED}/acl/uav-b")
        inbox = await a.subscribe(f"{FED}/acl/uav-a")
        await _reachable(b, inbox, f"{FED}/acl/uav-a")
        await b.publish(f"{FED}/acl/uav-b", b"for uav-b only")
        assert await _keys_until(inbox, (f"{FED}/acl/uav-a", MARK), b) == []
        # one link from the router to uav-a, in order: had the spy's subscription been
        # admitted, its message would be queued already
        assert spy.inbox.received == 0
        spy.close()
        inbox.close()
        print("denied: uav-a subscribing to acl/uav-b; allowed: acl/uav-a")


# -- the client settings: bad input is named ------------------------------------------------


def test_tls_and_password_settings_name_what_is_wrong(tmp_path: Path) -> None:
    base: dict[str, Any] = {"name": "uav-a", "federation": "traffic", "key": "k", "trust": "t"}
    base |= {"vocabulary": {}, "mapping": {}}
    connect = ["tls/127.0.0.1:7447"]
    lone_cert = {"root_ca_certificate": "ca.crt", "certificate": "uav-a.crt"}
    with pytest.raises(PlatformConfigError, match=r"transport.*tls.*certificate and private_key"):
        PlatformConfig.from_dict(
            {**base, "transport": {"mode": "client", "connect": connect, "tls": lone_cert}}
        )
    missing = ZenohConfig(
        mode="client", connect=tuple(connect), tls=ZenohTls(root_ca_certificate=tmp_path / "no")
    )
    with pytest.raises(TransportError, match=r"tls.root_ca_certificate: .*no: no such file"):
        missing.to_zenoh()
    (tmp_path / "empty").write_text("\n")
    for file, reason in (("absent", "cannot be read"), ("empty", "one non-empty line")):
        config = ZenohConfig(
            mode="client",
            connect=tuple(connect),
            usrpwd=ZenohUser(user="uav-a", password_file=tmp_path / file),
        )
        with pytest.raises(TransportError, match=rf"usrpwd.password_file: .*{file}: .*{reason}"):
            config.to_zenoh()
    # relative paths resolve against the config file's directory
    relative = ZenohConfig(
        mode="client",
        connect=tuple(connect),
        tls=ZenohTls(root_ca_certificate=Path("tls/ca.crt")),
        usrpwd=ZenohUser(user="uav-a", password_file=Path("tls/uav-a.password")),
    ).relative_to(tmp_path)
    assert relative.tls is not None and relative.usrpwd is not None
    assert relative.tls.root_ca_certificate == tmp_path / "tls" / "ca.crt"
    assert relative.usrpwd.password_file == tmp_path / "tls" / "uav-a.password"
    # … also in a platform's TOML file, like its key and trust file
    (tmp_path / "uav-a.toml").write_text(
        'name = "uav-a"\nfederation = "traffic"\nkey = "k"\ntrust = "t"\n'
        'vocabulary = "v.toml"\nmapping = "m.toml"\n[transport]\nmode = "client"\n'
        'connect = ["tls/127.0.0.1:7447"]\n'
        '[transport.tls]\nroot_ca_certificate = "tls/ca.crt"\n'
        '[transport.usrpwd]\nuser = "uav-a"\npassword_file = "tls/uav-a.password"\n'
    )
    loaded = PlatformConfig.load(tmp_path / "uav-a.toml").transport
    assert isinstance(loaded, ZenohConfig) and loaded.tls is not None and loaded.usrpwd
    assert loaded.tls.root_ca_certificate == tmp_path / "tls" / "ca.crt"
    assert loaded.usrpwd.password_file == tmp_path / "tls" / "uav-a.password"


def test_make_certs_keeps_secrets_private_names_platforms_and_is_idempotent(
    pki: dict[str, Path], tmp_path: Path
) -> None:
    tls = pki["tls"]
    assert tls.stat().st_mode & 0o777 == 0o700
    for name in ("ca.key", "router.key", "uav-a.key", "uav-a.password", "router-users.txt"):
        assert (tls / name).stat().st_mode & 0o777 == 0o600, name
    for name in ("uav-a", "uav-b"):
        subject = subprocess.run(
            ["openssl", "x509", "-in", str(tls / f"{name}.crt"), "-noout", "-subject"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        assert subject.strip().replace(" ", "") == f"subject=CN={name}"
    users = (tls / "router-users.txt").read_text().splitlines()
    assert users == [
        f"{n}:{(tls / f'{n}.password').read_text().strip()}" for n in ("uav-a", "uav-b")
    ]
    before = {p.name: p.read_bytes() for p in tls.iterdir()}
    _make_certs(tls, "uav-a", "uav-b")
    assert {p.name: p.read_bytes() for p in tls.iterdir()} == before
    bad = subprocess.run(
        [*MAKE_CERTS, "--dir", str(tmp_path / "x"), "--platform", "uav a"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert bad.returncode == 1 and "platform 'uav a': use 1-128 letters" in bad.stderr
