"""What the export and the import proxy share: whom they speak for, and the tasks they own."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Coroutine, Iterator
from typing import Any

from agents import check_name
from agents.transports import Subscription, Transport
from dyknow_core import DyKnowInstance

from ._sessions import SessionsProvider

__all__ = ["OnLost", "OwnedTasks", "ProxyBase"]

log = logging.getLogger(__name__)

OnLost = Callable[[Subscription[Any], str, str], None]
"""``on_lost(sub, what, meaning)``: a subscription of the proxy's, read to its end while not
closed (the transport ended it), as `AgentPlatform.ended` takes it."""


class OwnedTasks:
    """An owner's tasks: each named, kept until done, cancelled and awaited by `aclose`.

    The proxies', the operator console's and the Foxglove bridge's: what
    `asyncio.TaskGroup` gives, for an owner whose tasks start in plain calls
    (`ExportProxy.start_exporting` is synchronous and serves before and without
    ``async with``, which a group on Python 3.11 cannot): no task is left unowned.
    Unlike a group, a failed task does not cancel the others (a failed hook call must
    not end the loss reports): it is logged and counted in ``failures``.
    """

    __slots__ = ("_live", "failures", "name")

    def __init__(self, name: str) -> None:
        self.name = name
        self.failures = 0
        self._live: set[asyncio.Task[None]] = set()

    def __iter__(self) -> Iterator[asyncio.Task[None]]:
        return iter(list(self._live))

    def spawn(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        """Run ``coro`` as the task ``name``, owned here until it is done."""
        task = asyncio.get_running_loop().create_task(coro, name=name)
        self._live.add(task)
        task.add_done_callback(self._done)
        return task

    def _done(self, task: asyncio.Task[None]) -> None:
        self._live.discard(task)
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None:  # logged and counted; the other tasks go on
            self.failures += 1
            log.error("%s: %s failed", self.name, task.get_name(), exc_info=exc)

    async def aclose(self) -> None:
        """Cancel every task and wait until all are done (those they spawned meanwhile too)."""
        me = asyncio.current_task()
        while tasks := [t for t in self._live if t is not me]:
            for task in tasks:
                task.cancel()
            await asyncio.wait(tasks)


class ProxyBase:
    """The platform a proxy speaks for, its federation, transport, instance, sessions and tasks.

    ``on_lost``, when set, is told of each of its subscriptions the transport ends (its
    platform's `AgentPlatform.ended`: a loss); unset, such an end is logged at ERROR.
    """

    def __init__(
        self,
        kind: str,
        platform_name: str,
        federation: str,
        transport: Transport,
        instance: DyKnowInstance,
        sessions_provider: SessionsProvider,
    ) -> None:
        self.platform = check_name(platform_name)
        self.federation = check_name(federation, "federation")
        self.transport = transport
        self.instance = instance
        self.sessions = sessions_provider
        self._tasks = OwnedTasks(f"{kind}[{self.platform}]")
        self._kind = kind
        self.on_lost: OnLost | None = None

    def _ended(self, sub: Subscription[Any], what: str, meaning: str) -> None:
        """``sub``, read to its end by its consumer: lost unless closed (`on_lost`)."""
        if sub.closed:
            return
        if self.on_lost is not None:
            self.on_lost(sub, what, meaning)
        else:
            log.error(
                "%s[%s]: lost its %s (the transport ended the subscription): %s",
                self._kind,
                self.platform,
                what,
                meaning,
            )

    @property
    def task_failures(self) -> int:
        """How many of the proxy's tasks ended with an exception (each was logged)."""
        return self._tasks.failures
