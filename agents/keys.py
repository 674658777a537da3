"""Platform keys and the federation trust file, one command each.

::

    python -m agents.keys gen --platform uav-a --dir keys/
    python -m agents.keys trust --trust-file trust.json --federation demo keys/*.pub
    python -m agents.keys untrust --trust-file trust.json uav-c
    python -m agents.keys show --trust-file trust.json

The product CLI (``dyknow keys …``) reuses ``configure_parser`` and ``run``, or calls
``gen_keys`` / ``trust_keys`` / ``untrust`` / ``show`` directly. See ``docs/security.md``.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from ._exceptions import KeyFileError
from ._security import KeyPair, TrustStore, check_name, fingerprint, read_public_key

__all__ = ["configure_parser", "gen_keys", "main", "run", "show", "trust_keys", "untrust"]


class KeysError(Exception):
    """A key command could not do what was asked; the message says why (exit status 1)."""


def gen_keys(
    platform: str, directory: str | os.PathLike[str], *, force: bool = False
) -> tuple[KeyPair, Path, Path]:
    """Generate ``platform``'s key pair into ``directory``: ``(pair, private, public path)``."""
    try:
        check_name(platform)
    except ValueError as exc:
        raise KeysError(str(exc)) from None
    pair = KeyPair.generate(platform)
    try:
        key_path, pub_path = pair.save(directory, force=force)
    except KeyFileError as exc:
        raise KeysError(str(exc)) from None
    return pair, key_path, pub_path


def _open_trust(trust_file: Path, federation: str | None) -> tuple[TrustStore, bool]:
    """The trust store in ``trust_file`` (or a new one for ``federation``); True when new."""
    if trust_file.exists():
        try:
            store = TrustStore.load(trust_file)
        except KeyFileError as exc:
            raise KeysError(str(exc)) from None
        if federation is not None and federation != store.federation:
            raise KeysError(
                f"{trust_file} belongs to federation {store.federation!r}, not {federation!r}"
            )
        return store, False
    if federation is None:
        raise KeysError(f"{trust_file} does not exist; give --federation NAME to create it")
    try:
        return TrustStore(federation), True
    except ValueError as exc:
        raise KeysError(str(exc)) from None


def _existing_trust(trust_file: Path) -> TrustStore:
    """The trust store in ``trust_file``, which must exist (nothing to create here)."""
    if not trust_file.exists():
        raise KeysError(f"{trust_file}: no such trust file")
    return _open_trust(trust_file, None)[0]


def trust_keys(
    trust_file: str | os.PathLike[str],
    public_key_files: Sequence[str | os.PathLike[str]],
    *,
    federation: str | None = None,
    replace: bool = False,
) -> list[str]:
    """Add public key files to the trust file (created for ``federation`` if missing).

    All or nothing: if any file is unreadable or conflicts with a trusted key, the trust
    file is left untouched. Returns one line per platform saying what happened.
    """
    path = Path(trust_file)
    store, created = _open_trust(path, federation)
    lines = [f"{path}: federation {store.federation!r}" + (" (created)" if created else "")]
    seen: dict[str, Path] = {}
    changed = created
    for name in public_key_files:
        try:
            platform, public = read_public_key(name)
        except KeyFileError as exc:
            raise KeysError(str(exc)) from None
        if platform in seen:
            raise KeysError(f"{name}: platform {platform!r} is also in {seen[platform]}")
        seen[platform] = Path(name)
        if platform in store and store.public_key(platform) != public and not replace:
            raise KeysError(
                f"{name}: {path} already trusts another key for {platform!r} (fingerprint "
                f"{fingerprint(store.public_key(platform))}, new {fingerprint(public)}); "
                "use --replace to rotate it"
            )
        was = platform in store
        if store.add(platform, public, replace=replace):
            changed = True
            verb = "replaced" if was else "trusted"
        else:
            verb = "already trusted"
        lines.append(f"  {platform:<20} {fingerprint(public)}  {verb}")
    if changed:
        store.save(path)
    return lines


def untrust(trust_file: str | os.PathLike[str], platforms: Sequence[str]) -> list[str]:
    """Remove platforms from the trust file (their sessions are refused from then on).

    All or nothing: a name the file does not trust (a typo would otherwise look like a
    revocation that happened) changes nothing and is an error naming it.
    """
    path = Path(trust_file)
    store = _existing_trust(path)
    unknown = [p for p in platforms if p not in store]
    if unknown:
        raise KeysError(
            f"{path} does not trust {', '.join(map(repr, unknown))} "
            f"(it trusts: {', '.join(store) or 'nobody'}); nothing removed"
        )
    lines = [f"{path}: federation {store.federation!r}"]
    for platform in platforms:
        if store.remove(platform):
            lines.append(f"  {platform:<20} removed")
    if platforms:
        store.save(path)
    return lines


def show(trust_file: str | os.PathLike[str]) -> list[str]:
    """The platforms ``trust_file`` accepts, one line each with its key's fingerprint."""
    path = Path(trust_file)
    store = _existing_trust(path)
    lines = [f"{path}: federation {store.federation!r}, {len(store)} platform(s)"]
    for platform in store:
        lines.append(f"  {platform:<20} {fingerprint(store.public_key(platform))}")
    return lines


def configure_parser(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``gen``, ``trust``, ``untrust`` and ``show`` subcommands to ``parser``."""
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    gen = sub.add_parser("gen", help="generate a platform's Ed25519 key pair")
    gen.add_argument("--platform", required=True, help="platform name, e.g. uav-a")
    gen.add_argument("--dir", default="keys", type=Path, help="where to write (default: keys)")
    gen.add_argument(
        "--force", action="store_true", help="replace an existing private key (lock-out risk)"
    )
    gen.add_argument("--trust-file", type=Path, help="also trust the new key in this file")
    gen.add_argument("--federation", help="federation name when the trust file is created")

    trust = sub.add_parser("trust", help="add public key files to the federation trust file")
    trust.add_argument("--trust-file", required=True, type=Path)
    trust.add_argument("--federation", help="federation name (required to create the file)")
    trust.add_argument(
        "--replace", action="store_true", help="rotate: accept a new key for a known platform"
    )
    trust.add_argument("public_keys", nargs="+", type=Path, metavar="PUB", help="*.pub files")

    untrust_p = sub.add_parser("untrust", help="remove platforms from the trust file")
    untrust_p.add_argument("--trust-file", required=True, type=Path)
    untrust_p.add_argument("platforms", nargs="+", metavar="PLATFORM")

    show = sub.add_parser("show", help="list the platforms a trust file accepts")
    show.add_argument("--trust-file", required=True, type=Path)
    return parser


def run(args: argparse.Namespace) -> int:
    """Run a parsed key command; print what happened; 0 on success, 1 on a refusal."""
    try:
        if args.command == "gen":
            pair, key_path, pub_path = gen_keys(args.platform, args.dir, force=args.force)
            print(f"created {key_path} (private, mode 0600: keep it on {pair.platform} only)")
            print(f"created {pub_path} (public: add it to the federation's trust file)")
            print(f"fingerprint {pair.platform} {pair.fingerprint}")
            if args.trust_file is not None:
                lines = trust_keys(args.trust_file, [pub_path], federation=args.federation)
                print("\n".join(lines))
            else:
                print(f"next: python -m agents.keys trust --trust-file trust.json {pub_path}")
        elif args.command == "trust":
            lines = trust_keys(
                args.trust_file, args.public_keys, federation=args.federation, replace=args.replace
            )
            print("\n".join(lines))
        elif args.command == "untrust":
            print("\n".join(untrust(args.trust_file, args.platforms)))
        elif args.command == "show":
            print("\n".join(show(args.trust_file)))
    except KeysError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """The ``python -m agents.keys`` entry point."""
    parser = argparse.ArgumentParser(
        prog="python -m agents.keys",
        description="DyKnow Federation platform keys and the federation trust file.",
    )
    configure_parser(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
