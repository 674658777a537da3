"""The proxies' owned tasks: named, awaited on close, a failure logged and counted."""

from __future__ import annotations

import asyncio
import logging

import pytest

from federation._proxy_base import OwnedTasks


async def test_a_failed_task_is_logged_and_counted_and_the_others_go_on(
    caplog: pytest.LogCaptureFixture,
) -> None:
    tasks = OwnedTasks("import[uav-b]")
    stop = asyncio.Event()

    async def fail() -> None:
        raise RuntimeError("boom")

    spawned = tasks.spawn(stop.wait(), "import[uav-b].receive")
    with caplog.at_level(logging.ERROR, logger="federation._proxy_base"):
        failed = tasks.spawn(fail(), "import[uav-b].resend")
        await asyncio.wait([failed])
        await asyncio.sleep(0)
    assert tasks.failures == 1 and "import[uav-b].resend failed" in caplog.text
    assert spawned.get_name() == "import[uav-b].receive" and not spawned.done()
    assert list(tasks) == [spawned]
    await tasks.aclose()
    assert spawned.cancelled() and list(tasks) == []


async def test_close_cancels_what_the_tasks_spawn_while_closing() -> None:
    tasks = OwnedTasks("export[uav-a]")
    late: list[asyncio.Task[None]] = []

    async def spawner() -> None:
        try:
            await asyncio.Event().wait()
        finally:
            late.append(tasks.spawn(asyncio.Event().wait(), "export[uav-a].late"))

    tasks.spawn(spawner(), "export[uav-a].spawner")
    await asyncio.sleep(0)
    await tasks.aclose()
    assert len(late) == 1 and late[0].cancelled() and tasks.failures == 0
