"""`agents.run`: asyncio.run on uvloop where installed, asyncio's own loop on request."""

from __future__ import annotations

import asyncio
import sys

import pytest

from agents import event_loop_name, run


async def _loop_type() -> str:
    return type(asyncio.get_running_loop()).__module__


def test_run_returns_the_result_on_the_named_loop() -> None:
    module = run(_loop_type())
    assert module.startswith("uvloop") == (event_loop_name() == "uvloop")


def test_the_environment_keeps_asyncio(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DYKNOW_EVENT_LOOP", "asyncio")
    assert event_loop_name() == "asyncio"
    assert run(_loop_type()).startswith("asyncio")


@pytest.mark.skipif(sys.platform == "win32", reason="uvloop is no dependency on Windows")
def test_uvloop_when_installed(monkeypatch: pytest.MonkeyPatch) -> None:
    import uvloop  # noqa: F401  (a dependency: missing, this fails rather than skips)

    monkeypatch.delenv("DYKNOW_EVENT_LOOP", raising=False)
    assert event_loop_name() == "uvloop"
    assert run(_loop_type()).startswith("uvloop")
