"""Platform keys and the federation trust file: what each ``dyknow keys`` command does.

::

    dyknow keys gen --platform uav-a --dir keys/
    dyknow keys trust --trust-file trust.json --federation demo keys/*.pub
    dyknow keys untrust --trust-file trust.json uav-c
    dyknow keys show --trust-file trust.json

The CLI (``federation.cli``) calls ``gen_keys`` / ``trust_keys`` / ``untrust`` / ``show``;
programs (tests, the demo, deploy scripts) call them directly. See ``docs/security.md``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from ._exceptions import KeyFileError
from ._security import KeyPair, TrustStore, check_name, fingerprint, read_public_key

__all__ = ["KeysError", "check_trust_file", "gen_keys", "show", "trust_keys", "untrust"]


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


def check_trust_file(trust_file: str | os.PathLike[str], federation: str | None = None) -> None:
    """Raise KeysError if ``trust_keys`` would refuse this trust file and federation."""
    _open_trust(Path(trust_file), federation)


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
