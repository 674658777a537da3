#!/usr/bin/env python3
"""Certificates and passwords for an authenticated zenoh router (config/router-secure.json5).

Makes, with the system's ``openssl`` (no Python package needed), into ``--dir``
(default ``deploy/config/keys/tls/``, which git and the Docker build ignore):

- ``ca.crt``/``ca.key``: the federation's own certificate authority (EC P-256);
- ``router.crt``/``router.key``: the router's certificate, its names in subjectAltName
  (``--router-name``: the addresses and host names platforms connect to);
- ``<platform>.crt``/``<platform>.key``: one client certificate per platform, with
  CN = the platform's name: the router's access control knows a platform by it;
- ``<platform>.password``: a random password per platform (user = the platform's name),
  and ``router-users.txt``: every ``user:password`` line, the router's usrpwd dictionary.

Private keys and passwords are written mode 0600 (the directory 0700). It is idempotent:
what exists is kept (delete a file to make it anew; a new CA means new certificates for
all). Run from the repository root::

    python3 deploy/make_certs.py                                  # uav-a uav-b uav-c operator
    python3 deploy/make_certs.py --dir /tmp/tls --platform uav-a --platform uav-b \\
        --router-name 127.0.0.1 --router-name localhost
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import re
import secrets
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_DIR = HERE / "config" / "keys" / "tls"
DEFAULT_PLATFORMS = ("uav-a", "uav-b", "uav-c", "operator")
# the router's address on the compose network (docker-compose.yml) and the usual local names
DEFAULT_ROUTER_NAMES = (
    "router",
    "mosquitto",
    "localhost",
    "127.0.0.1",
    "172.28.0.10",
    "172.29.0.10",
)
DAYS = 825
_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,128}$")
_HOST = re.compile(r"^[A-Za-z0-9]([A-Za-z0-9-]{0,62})(\.[A-Za-z0-9]([A-Za-z0-9-]{0,62}))*$")


class CertError(Exception):
    """A certificate could not be made: says which and why."""


def _openssl() -> str:
    found = shutil.which("openssl") or (
        "/usr/bin/openssl" if Path("/usr/bin/openssl").exists() else None
    )
    if found is None:
        raise CertError("openssl not found (install it: apt-get install openssl)")
    return found


def _run(args: Sequence[str]) -> None:
    done = subprocess.run([_openssl(), *args], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise CertError(f"openssl {args[0]} failed: {done.stderr.strip() or done.stdout.strip()}")


def _private(path: Path) -> None:
    """An EC P-256 private key (PKCS#8 PEM) at ``path``, mode 0600 from the start."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    os.close(fd)
    _run(["genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(tmp)])
    os.chmod(tmp, 0o600)
    tmp.replace(path)  # a crash never leaves half a key under the real name


def _write_secret(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    tmp.replace(path)


def _san(names: Iterable[str]) -> str:
    entries = []
    for name in names:
        try:
            ipaddress.ip_address(name)
            entries.append(f"IP:{name}")
        except ValueError:
            if not _HOST.match(name):
                raise CertError(f"--router-name {name!r}: not a host name or IP address") from None
            entries.append(f"DNS:{name}")
    return ",".join(entries)


def _sign(out: Path, key: Path, ca: tuple[Path, Path], cn: str, extensions: Sequence[str]) -> None:
    """A certificate for ``key`` with CN ``cn``, signed by the CA, with v3 ``extensions``."""
    with tempfile.TemporaryDirectory() as tmp:
        csr = Path(tmp) / "req.csr"
        ext = Path(tmp) / "ext.cnf"
        ext.write_text("[v3]\n" + "\n".join(extensions) + "\n", encoding="utf-8")
        _run(["req", "-new", "-key", str(key), "-subj", f"/CN={cn}", "-out", str(csr)])
        _run(
            [
                "x509", "-req", "-in", str(csr), "-CA", str(ca[0]), "-CAkey", str(ca[1]),
                "-set_serial", str(secrets.randbits(63)), "-days", str(DAYS), "-sha256",
                "-extfile", str(ext), "-extensions", "v3", "-out", str(out),
            ]
        )  # fmt: skip


def make_certs(
    directory: str | Path,
    platforms: Iterable[str] = DEFAULT_PLATFORMS,
    *,
    router_names: Iterable[str] = DEFAULT_ROUTER_NAMES,
    say: Callable[[str], None] = print,
) -> Path:
    """Make the CA, the router's and each platform's certificate and password; return the dir."""
    out = Path(directory)
    platforms = list(dict.fromkeys(platforms))
    for name in platforms:
        if not _NAME.match(name):
            raise CertError(f"platform {name!r}: use 1-128 letters, digits, '-', '_', '.'")
        if name in ("ca", "router"):
            raise CertError(f"platform {name!r}: the name is taken by the CA/router files")
    router_names = list(router_names)
    if not router_names:
        raise CertError("the router needs at least one name (--router-name)")
    san = _san(router_names)
    tell = say
    out.mkdir(parents=True, exist_ok=True)
    os.chmod(out, 0o700)
    ca = (out / "ca.crt", out / "ca.key")
    if not ca[1].exists():
        _private(ca[1])
        ca[0].unlink(missing_ok=True)
    if not ca[0].exists():
        _run(
            [
                "req", "-x509", "-new", "-key", str(ca[1]), "-subj", "/CN=dyknow federation CA",
                "-days", str(DAYS), "-sha256", "-addext", "basicConstraints=critical,CA:TRUE",
                "-addext", "keyUsage=critical,keyCertSign,cRLSign", "-out", str(ca[0]),
            ]
        )  # fmt: skip
        tell(f"created {ca[0]} (the CA: every router and platform trusts it)")
    leaf = ["basicConstraints=critical,CA:FALSE", "keyUsage=critical,digitalSignature"]
    wanted = [
        ("router", [*leaf, "extendedKeyUsage=serverAuth,clientAuth", f"subjectAltName={san}"])
    ]
    wanted += [(p, [*leaf, "extendedKeyUsage=clientAuth,serverAuth"]) for p in platforms]
    for cn, extensions in wanted:
        crt, key = out / f"{cn}.crt", out / f"{cn}.key"
        if not key.exists():
            _private(key)
            crt.unlink(missing_ok=True)
        if crt.exists():
            tell(f"keep {crt} (exists; delete it to make a new one)")
            continue
        _sign(crt, key, ca, cn, extensions)
        tell(f"created {crt} (CN={cn})")
    users = []
    for name in platforms:
        pw = out / f"{name}.password"
        if not pw.exists():
            _write_secret(pw, secrets.token_urlsafe(24) + "\n")
            tell(f"created {pw} (user {name})")
        users.append(f"{name}:{pw.read_text(encoding='utf-8').strip()}\n")
    _write_secret(out / "router-users.txt", "".join(users))
    tell(f"wrote {out / 'router-users.txt'} ({len(users)} users)")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--dir", type=Path, default=DEFAULT_DIR, help="where to write")
    parser.add_argument(
        "--platform", action="append", help="a platform (repeat); default: the traffic demo's"
    )
    parser.add_argument(
        "--router-name", action="append", help="a name or address of the router (repeat)"
    )
    args = parser.parse_args(argv)
    try:
        make_certs(
            args.dir,
            args.platform or DEFAULT_PLATFORMS,
            router_names=args.router_name or DEFAULT_ROUTER_NAMES,
        )
    except (CertError, OSError) as exc:
        print(f"make_certs: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
