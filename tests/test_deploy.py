"""The deploy files (deploy/): compose topology, platform configs, keys step, router config.

No Docker engine runs where these tests run. ``docker compose config -q`` (the CLI
plugin) or Debian's ``docker-compose config -q`` (which `make test` installs when neither
is there) validates both compose files: it needs no engine. The files are also checked
structurally with PyYAML (services, fixed addresses in the subnet, mounts, commands,
depends_on): the topology that ``config`` would not catch.

The platform configs are loaded with ``PlatformConfig.load`` and their key, trust,
vocabulary and mapping files read, after generating keys into a temporary copy of
deploy/config with what deploy/make-keys.sh runs (``dyknow keys``' functions).
"""

from __future__ import annotations

import fnmatch
import ipaddress
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path, PurePosixPath
from typing import Any

import pytest
import yaml
import zenoh

from agents.keys import gen_keys, trust_keys
from federation import PlatformConfig
from federation._platform import MqttSettings, ZenohSettings, _read_files

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
CONFIG = DEPLOY / "config"
PLATFORMS = ("uav-a", "uav-b", "uav-c", "operator")
FEDERATION = "traffic"
MOUNT = PurePosixPath("/etc/dyknow")

# compose file -> (the hub service, its port, the config subdirectory, transport kind)
TOPOLOGIES = {
    # the authenticated router: mutual TLS, passwords, access control (router-secure.json5)
    "docker-compose.yml": ("router", 7447, "secure/", "zenoh"),
    "docker-compose.mqtt.yml": ("mosquitto", 8883, "mqtt/", "mqtt"),
}


def _compose(name: str) -> dict[str, Any]:
    data = yaml.safe_load((DEPLOY / name).read_text())
    assert isinstance(data, dict), name
    return data


def _address(service: dict[str, Any]) -> tuple[str, ipaddress.IPv4Address]:
    networks = service["networks"]
    assert isinstance(networks, dict) and len(networks) == 1, networks
    (net, settings), *_ = networks.items()
    return net, ipaddress.IPv4Address(settings["ipv4_address"])


def _mounts(service: dict[str, Any]) -> dict[PurePosixPath, Path]:
    """Container path -> host path, for the read-only bind mounts of a service."""
    out: dict[PurePosixPath, Path] = {}
    for volume in service.get("volumes", []):
        host, container, mode = volume.split(":")
        assert mode == "ro", f"{volume}: mount read-only"
        out[PurePosixPath(container)] = (DEPLOY / host).resolve()
    return out


@pytest.fixture(scope="module")
def keyed_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of deploy/config with keys and trust file, made as make-keys.sh makes them."""
    config = tmp_path_factory.mktemp("deploy") / "config"
    shutil.copytree(CONFIG, config, ignore=shutil.ignore_patterns("keys"))
    keys = config / "keys"
    pubs = [gen_keys(p, keys)[2] for p in PLATFORMS]
    trust_keys(keys / "trust.json", pubs, federation=FEDERATION)
    # and the certificates and passwords, as make-keys.sh makes them (make_certs.py)
    certs = [sys.executable, str(DEPLOY / "make_certs.py"), "--dir", str(keys / "tls")]
    certs += [f"--platform={p}" for p in PLATFORMS]
    done = subprocess.run(certs, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    return config


def test_make_keys_script_runs_the_same_commands() -> None:
    script = (DEPLOY / "make-keys.sh").read_text()
    assert script.startswith("#!/usr/bin/env bash\n")
    assert "set -euo pipefail" in script
    assert "platforms=(uav-a uav-b uav-c operator)" in script
    assert f'federation="{FEDERATION}"' in script
    # one Python runs every command (the CLI's main, then the deploy scripts' mains)
    assert '["keys", "gen", "--platform", platform, "--dir", keys_dir]' in script
    assert '["keys", "trust", "--trust-file", trust_file, "--federation", federation' in script
    assert 'run(script("make_hub_configs"), ["--trust-file", trust_file, "--out"' in script
    assert 'run(script("make_certs"), ["--dir", f"{keys_dir}/tls"' in script
    # the command it prints is deploy/README.md's: the project named, as the later
    # `docker compose -p dyknow … logs operator` expects
    readme = (DEPLOY / "README.md").read_text()
    printed = "docker compose -p dyknow -f deploy/docker-compose.yml up --build"
    assert printed in script and printed in readme
    assert "/deploy/config/keys/" in (DEPLOY.parent / ".gitignore").read_text().splitlines()


def _run_make_keys(tmp: Path, python3: str) -> tuple[subprocess.CompletedProcess[str], Path]:
    """Run a copy of make-keys.sh with pip's long-path `dyknow` script on the PATH.

    pip writes `#!/bin/sh` and an exec line into the script when the venv's path has a
    space or is too long for a shebang. `python3` on the PATH runs the shell line
    ``python3``. The copy has no .venv beside it: python3 is the next choice after the CLI's.
    """
    deploy = tmp / "deploy"
    deploy.mkdir()
    for name in ("make-keys.sh", "make_certs.py", "make_hub_configs.py"):
        shutil.copy(DEPLOY / name, deploy / name)
    config = deploy / "config"
    shutil.copytree(CONFIG, config, ignore=shutil.ignore_patterns("keys"))
    bin_dir = tmp / "bin"
    bin_dir.mkdir()
    dyknow = bin_dir / "dyknow"
    dyknow.write_text(
        "#!/bin/sh\n"
        """'''exec' "/a venv/with a space/bin/python" "$0" "$@"\n"""
        "' '''\n"
        "from federation.cli import main\n"
    )
    (bin_dir / "python3").write_text(f"#!/bin/sh\n{python3}\n")
    for script in (dyknow, bin_dir / "python3"):
        script.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k != "PYTHON"}
    env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = str(DEPLOY.parent)
    done = subprocess.run(
        ["bash", str(deploy / "make-keys.sh"), str(config)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        env=env,
    )
    return done, config / "keys"


def test_make_keys_skips_a_cli_whose_first_line_is_not_a_python(tmp_path: Path) -> None:
    done, keys = _run_make_keys(tmp_path, f'exec "{sys.executable}" "$@"')
    assert done.returncode == 0, done.stdout + done.stderr
    assert all((keys / f"{p}.key").is_file() for p in PLATFORMS)
    assert (keys / "trust.json").is_file()
    assert "Keys and trust file are in" in done.stdout


def test_make_keys_fails_when_no_key_was_made(tmp_path: Path) -> None:
    # an interpreter that reads the program, does nothing, and exits 0
    done, keys = _run_make_keys(tmp_path, "cat >/dev/null")
    assert done.returncode != 0
    assert "no key" in done.stderr and "PYTHON" in done.stderr
    assert "Keys and trust file are in" not in done.stdout
    assert not (keys / "uav-a.key").exists()


@pytest.mark.parametrize("subdir", ["", "mqtt/", "secure/"])
@pytest.mark.parametrize("platform", PLATFORMS)
def test_platform_config_is_valid(keyed_config: Path, platform: str, subdir: str) -> None:
    path = keyed_config / subdir / f"{platform}.toml"
    config = PlatformConfig.load(path)
    assert config.name == platform
    assert config.federation == FEDERATION
    files = _read_files(config, str(path))  # key, trust, vocabulary, mapping: all readable
    assert files.keys.platform == platform
    assert set(files.trust) == set(PLATFORMS)
    if subdir == "secure/":
        assert isinstance(config.transport, ZenohSettings)
        assert config.transport.mode == "client"
        assert config.transport.connect == ("tls/172.28.0.10:7447",)
        tls, user = config.transport.tls, config.transport.usrpwd
        assert tls is not None and user is not None and user.user == platform
        assert tls.certificate == Path(f"/etc/dyknow/tls/{platform}.crt")
        # encrypted end to end and the audit sealed: the defaults, not switched off
        assert config.security.encrypt and config.security.audit == "sealed"
    elif subdir:
        assert isinstance(config.transport, MqttSettings)
        assert config.transport.host == "172.29.0.10"
        assert config.transport.client_id == f"dyknow-{platform}"
    else:
        assert isinstance(config.transport, ZenohSettings)
        assert config.transport.mode == "client"
        assert config.transport.connect == ("tcp/172.28.0.10:7447",)
    if platform != "operator":  # the UAVs track cars; the operator maps no car labels
        assert files.mapping.to_local("car5-state") == "car/car5/state"
    # a sharing rule naming labels the platform maps none of is dead (a leftover)
    for rule in config.sharing.rules:
        for pattern in rule.labels:
            assert fnmatch.filter(files.mapping.mapped, pattern), (rule.name, pattern)


def test_router_config_is_zenoh_json5() -> None:
    text = (CONFIG / "router.json5").read_text()
    zenoh.Config.from_json5(text)
    for hint in ("tls", "enable_mtls", "usrpwd", "access_control"):
        assert hint in text, f"router.json5 should say where {hint} goes"
    assert '"tcp/0.0.0.0:7447"' in text


@pytest.mark.parametrize("file", sorted(TOPOLOGIES))
def test_compose_topology(file: str) -> None:
    hub, port, subdir, kind = TOPOLOGIES[file]
    compose = _compose(file)
    services = compose["services"]
    assert set(services) == {hub, *PLATFORMS}
    ((net_name, net),) = compose["networks"].items()
    subnet = ipaddress.IPv4Network(net["ipam"]["config"][0]["subnet"])
    addresses = {}
    for name, service in services.items():
        net_of, address = _address(service)
        assert net_of == net_name, f"{file}: {name} is not on {net_name}"
        assert address in subnet, f"{file}: {name} {address} not in {subnet}"
        assert address not in (subnet.network_address, subnet.broadcast_address)
        assert address != next(subnet.hosts()), f"{file}: {name} takes the gateway address"
        addresses[name] = address
    assert len(set(addresses.values())) == len(addresses), f"{file}: addresses repeat"

    for name in PLATFORMS:
        service = services[name]
        assert service["build"] == {"context": "..", "dockerfile": "deploy/Dockerfile"}
        assert service["depends_on"] == [hub]
        command = service["command"]
        # the operator's process serves the web console on the published port
        verb = "console" if name == "operator" else "node"
        assert command[:2] == [verb, "--config"], f"{file}: {name}: {command}"
        if name == "operator":
            assert command[3:] == ["--host", "0.0.0.0", "--port", "8080"]
        mounts = _mounts(service)
        container_config = PurePosixPath(command[2])
        assert container_config == MOUNT / f"{subdir}{name}.toml"
        assert mounts[container_config] == CONFIG / f"{subdir}{name}.toml"
        # every file the config names is mounted where the config's relative path points
        config = tomllib.loads(mounts[container_config].read_text())
        for key in ("key", "trust", "vocabulary", "mapping", "application"):
            if key not in config:
                continue  # the operator runs no application of its own
            target = PurePosixPath(*_normalize(container_config.parent / config[key]).parts)
            assert target in mounts, f"{file}: {name}: {key} {target} is not mounted"
        # its own private keys only (its identity, its TLS key; over zenoh its password)
        keys = sorted(m for m in mounts if m.suffix in (".key", ".password"))
        own = [MOUNT / "keys" / f"{name}.key", MOUNT / "tls" / f"{name}.key"]
        if kind == "zenoh":
            own += [MOUNT / "tls" / f"{name}.password"]
        assert keys == sorted(own), f"{file}: {name} mounts {keys}"
        if kind == "mqtt":  # the broker admits TLS clients only: every file is mounted
            assert MOUNT / "tls" / "ca.crt" in mounts
            for field, path in config["transport"]["tls"].items():
                assert PurePosixPath(path) in mounts, f"{file}: {name}: tls.{field}"
        # the transport points at the hub's fixed address
        transport = config["transport"]
        assert transport["kind"] == kind
        if kind == "zenoh":
            assert transport["connect"] == [f"tls/{addresses[hub]}:{port}"]
            # every TLS file and the password file mounted where the config says
            files = [*transport["tls"].values(), transport["usrpwd"]["password_file"]]
            for path in (f for f in files if isinstance(f, str)):
                assert PurePosixPath(path) in mounts, f"{file}: {name}: {path} is not mounted"
        else:
            assert (transport["host"], transport["port"]) == (str(addresses[hub]), port)

    if kind == "zenoh":
        router = services[hub]
        assert router["command"] == [
            "router",
            "--zenoh-config",
            str(MOUNT / "router-secure.json5"),
        ]
        tls_dir = CONFIG / "keys" / "tls"
        # the CA's certificate but never its key: certificates are made elsewhere
        assert _mounts(router) == {
            MOUNT / "router-secure.json5": CONFIG / "router-secure.json5",
            **{
                MOUNT / "tls" / f: (tls_dir / f).resolve()
                for f in ("ca.crt", "router.crt", "router.key", "router-users.txt")
            },
        }
    else:
        broker = services[hub]
        assert broker["image"].startswith("eclipse-mosquitto:")
        mounts = _mounts(broker)
        conf = mounts[PurePosixPath("/mosquitto/config/mosquitto.conf")]
        assert conf == CONFIG / "mosquitto-secure.conf"
        text = conf.read_text()
        assert f"listener {port}" in text and "require_certificate true" in text
        # every file the broker's config names is mounted there
        for line in text.splitlines():
            word, _, value = line.partition(" ")
            if word in ("cafile", "certfile", "keyfile", "acl_file"):
                assert PurePosixPath(value) in mounts, f"{file}: broker {word} {value}"


@pytest.mark.parametrize("file", sorted(TOPOLOGIES))
def test_only_the_operator_console_port_is_published(file: str) -> None:
    services = _compose(file)["services"]
    # The console's port inside the container on the same host port, and nothing else:
    # hub and platforms are reachable on the private network only.
    published = {name: s["ports"] for name, s in services.items() if "ports" in s}
    assert published == {"operator": ["8080:8080"]}, f"{file}: {published}"


@pytest.mark.parametrize("file", sorted(TOPOLOGIES))
def test_the_operator_console_token_comes_from_the_environment(file: str) -> None:
    services = _compose(file)["services"]
    # `DYKNOW_CONSOLE_TOKEN=… docker compose up` chooses it; unset, the console makes one
    # and prints the URL with it in the operator's log (docs/console.md)
    env = services["operator"]["environment"]
    assert env == {
        "DYKNOW_CONSOLE_TOKEN": "${DYKNOW_CONSOLE_TOKEN:-}",
        "DYKNOW_CONSOLE_ALLOW_HOSTS": "${DYKNOW_CONSOLE_ALLOW_HOSTS:-}",
    }, f"{file}: {env}"
    assert not [n for n, s in services.items() if n != "operator" and "environment" in s]


def _normalize(path: PurePosixPath) -> PurePosixPath:
    parts: list[str] = []
    for part in path.parts:
        if part == "..":
            parts.pop()
        else:
            parts.append(part)
    return PurePosixPath(*parts)


def test_dockerfile() -> None:
    text = (DEPLOY / "Dockerfile").read_text()
    lines = [line.strip() for line in text.splitlines() if line.strip() and line[0] != "#"]
    assert lines[0] == "FROM python:3.11-slim"
    assert any(line.startswith("RUN pip install .") for line in lines)
    user = [line for line in lines if line.startswith("USER ")]
    assert user and user[-1] not in ("USER root", "USER 0"), "run as a non-root user"
    assert 'ENTRYPOINT ["dyknow"]' in lines
    assert "deploy/config/keys" in (DEPLOY / "Dockerfile.dockerignore").read_text()


def _compose_command() -> list[str] | None:
    """``docker compose`` (the plugin) or Debian's ``docker-compose``; None without both."""
    docker = shutil.which("docker")
    if docker is not None:
        probe = subprocess.run(
            [docker, "compose", "version"], capture_output=True, text=True, timeout=20, check=False
        )
        if probe.returncode == 0:
            return [docker, "compose"]
    legacy = shutil.which("docker-compose")
    return [legacy] if legacy is not None else None


@pytest.mark.parametrize("file", sorted(TOPOLOGIES))
def test_compose_config_validates(file: str, keyed_config: Path) -> None:
    """``docker compose config -q`` (or Debian's ``docker-compose``), plus a structural check.

    `make test` installs Debian's docker-compose when neither is there; in CI a missing
    one fails. Validation needs no Docker engine. The structural check covers what
    ``config`` rejects in these files: a top-level mapping of known keys, services with an
    image or a build, list-form commands, and anchors/merge keys that resolve.
    """
    command = _compose_command()
    if command is None:
        message = "neither 'docker compose' nor 'docker-compose' (make test installs it)"
        if os.environ.get("CI"):
            pytest.fail(message)
    else:
        # config resolves bind-mount sources: run it on a copy that has the keys
        tmp = keyed_config.parent
        shutil.copy(DEPLOY / file, tmp / file)
        result = subprocess.run(
            [*command, "-f", str(tmp / file), "config", "-q"],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert result.returncode == 0, result.stderr
    compose = _compose(file)
    # no top-level "name": docker-compose 1.29 (Debian's) refuses it; `-p` names the project
    allowed = {"services", "networks", "volumes", "configs", "secrets"}
    extra = {k for k in compose if not k.startswith("x-")} - allowed
    assert not extra, f"{file}: unknown top-level keys {extra}"
    for name, service in compose["services"].items():
        assert "image" in service or "build" in service, f"{file}: {name}"
        assert "<<" not in service, f"{file}: {name}: merge key did not resolve"
        if "command" in service:
            assert isinstance(service["command"], list), f"{file}: {name}"
            assert all(isinstance(x, str) for x in service["command"])
