"""Where a node's local channel lives (`federation._local.channel_path`): under
``$XDG_RUNTIME_DIR`` when it is set, without asking for the temporary directory at all
(finding one may fail, and costs a look-up); under ``<tmp>/dyknow-<uid>`` otherwise, or
when the runtime path is too long for a socket."""

from __future__ import annotations

import asyncio
import os
import shutil
import stat
import tempfile
import uuid
from pathlib import Path

import pytest

from agents._security import KeyPair
from federation import PlatformConfig
from federation._local import (
    _SUN_PATH,
    LocalChannelError,
    _private_dir,
    channel_path,
    via_node,
)


def _config(tmp_path: Path) -> PlatformConfig:
    return PlatformConfig(
        name="uav-a",
        federation=f"chan-{uuid.uuid4().hex[:12]}",
        key=tmp_path / "uav-a.key",
        trust=tmp_path / "trust.json",
        vocabulary={},
        mapping={},
    )


def _no_tmp() -> str:
    raise FileNotFoundError("No usable temporary directory found")


def test_the_runtime_directory_is_used_without_asking_for_the_temporary_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """$XDG_RUNTIME_DIR set, no usable temporary directory: the channel's path and its
    private directories are made all the same (0700), none of them under <tmp>."""
    # a short one (a socket's path is short): tmp_path's own would be hashed under <tmp>
    runtime = Path(tempfile.mkdtemp(prefix="xdg-"))
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
    monkeypatch.setattr(tempfile, "gettempdir", _no_tmp)
    config, keys = _config(tmp_path), KeyPair.generate("uav-a")
    try:
        path = channel_path(config, keys)
        assert path == runtime / "dyknow" / config.federation / f"uav-a-{keys.fingerprint}.sock"
        assert _private_dir(path.parent) is True
        for made in (runtime / "dyknow", path.parent):
            assert stat.S_IMODE(made.stat().st_mode) == 0o700
    finally:
        shutil.rmtree(runtime)


def test_a_runtime_path_too_long_for_a_socket_goes_under_the_temporary_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The one case $XDG_RUNTIME_DIR needs <tmp>: a hashed short path there."""
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / ("r" * 120)))
    config, keys = _config(tmp_path), KeyPair.generate("uav-a")
    path = channel_path(config, keys)
    assert path.parent == Path(tempfile.gettempdir()) / f"dyknow-{os.getuid()}"
    assert len(os.fsencode(path)) <= _SUN_PATH and path.suffix == ".sock"
    monkeypatch.setattr(tempfile, "gettempdir", _no_tmp)
    # needed here and missing: the module's error for a channel this host cannot have, an
    # OSError (what the node's start and the commands report in one line), saying why
    with pytest.raises(LocalChannelError) as raised:
        channel_path(config, keys)
    said = str(raised.value)
    assert "cannot place the local channel of platform 'uav-a'" in said
    assert "too long for a socket" in said and "No usable temporary directory" in said
    assert "set TMPDIR" in said and "XDG_RUNTIME_DIR to a shorter one" in said
    assert isinstance(raised.value, OSError) and raised.value.__cause__ is None


def test_without_a_runtime_directory_no_temporary_one_is_a_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No $XDG_RUNTIME_DIR and no usable <tmp>: LocalChannelError naming both, for the
    node's start (`LocalChannel`) and a command reaching its node (`via_node`) alike."""
    monkeypatch.delenv("XDG_RUNTIME_DIR", raising=False)
    monkeypatch.setattr(tempfile, "gettempdir", _no_tmp)
    config, keys = _config(tmp_path), KeyPair.generate("uav-a")
    with pytest.raises(LocalChannelError, match=r"without \$XDG_RUNTIME_DIR .* set TMPDIR"):
        channel_path(config, keys)
    keys.save(tmp_path)  # uav-a.key, the config's key: the command reads it

    async def reach() -> None:
        async for _ in via_node(config, {"platforms": True}):
            pass

    with pytest.raises(LocalChannelError, match="no usable one"):
        asyncio.run(reach())
