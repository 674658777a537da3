"""The in-memory transport: several platforms in one process, and the tests' double."""

from __future__ import annotations

import asyncio
import contextlib
import functools
from collections.abc import Callable

from .._exceptions import TransportError
from ._base import (
    Handle,
    Inbox,
    Message,
    Presence,
    QueryFilter,
    QueryHandler,
    Replies,
    Reply,
    Screened,
    Subscription,
    Transport,
    _ignore,
    key_matches,
)

# (key expression, key) → whether it matches: the hub's few subscriptions see the same
# keys again and again, and matching splits both strings each time
_matched: dict[tuple[str, str], bool] = {}
_MAX_MATCHED = 4096


def _match_remembered(expr: str, key: str) -> bool:
    if len(_matched) >= _MAX_MATCHED:
        _matched.clear()
    hit = _matched[(expr, key)] = key_matches(expr, key)
    return hit


async def _ask(handler: QueryHandler, key_expr: str, payload: bytes) -> bytes | None:
    return await handler(key_expr, payload)


class MemoryHub:
    """What connects in-memory transports: the same hub is the same network."""

    def __init__(self) -> None:
        self.subscribers: list[tuple[str, Inbox[Message] | Screened]] = []
        self.queryables: list[tuple[str, QueryHandler]] = []
        self.tokens: dict[str, int] = {}
        self.watchers: list[tuple[str, Inbox[Presence]]] = []

    def transport(self) -> MemoryTransport:
        """A new transport attached to this hub."""
        return MemoryTransport(self)

    def _presence(self, key: str, alive: bool) -> None:
        for expr, inbox in list(self.watchers):
            if key_matches(expr, key):
                inbox.put(Presence(key, alive))


class MemoryTransport(Transport):
    """Delivers within one process through a MemoryHub; same semantics as the others."""

    name = "memory"

    def __init__(self, hub: MemoryHub | None = None) -> None:
        super().__init__()
        self.hub = hub or MemoryHub()
        self._handles: list[Handle] = []
        self._subs: list[Subscription[Message] | Subscription[Presence]] = []

    async def open(self) -> None:
        """Nothing to connect."""

    async def aclose(self) -> None:
        """Undeclare everything this transport declared."""
        if self._state == "closed":
            return
        self._state = "closed"
        for h in list(self._handles):
            h.close()
        for s in list(self._subs):
            s.close()

    async def publish(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        """Deliver to every matching subscriber in the hub."""
        self._put(key, payload, attachment)

    @property
    def publishes_nowait(self) -> bool:
        """True (a put into the hub never waits), unless a subclass overrides ``publish``."""
        return type(self).publish is MemoryTransport.publish

    def publish_nowait(self, key: str, payload: bytes) -> None:
        """Publish ``payload`` on ``key`` now."""
        if not self.publishes_nowait:
            super().publish_nowait(key, payload)  # refuses: a subclass's `publish` sees all
            return
        self._put(key, payload, None)

    def _put(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        self._check_open()
        msg = Message(key, payload, attachment)
        matched = _matched
        for expr, inbox in self.hub.subscribers:
            hit = matched.get((expr, key))
            if hit is None:
                hit = _match_remembered(expr, key)
            if hit:
                inbox.put(msg)

    def has_subscribers(self, key: str) -> bool:
        """Whether a subscription in the hub matches ``key`` (a put would reach it)."""
        self._check_open()
        matched = _matched
        for expr, _ in self.hub.subscribers:
            hit = matched.get((expr, key))
            if hit is None:
                hit = _match_remembered(expr, key)
            if hit:
                return True
        return False

    async def subscribe(
        self, key_expr: str, *, buffer_size: int = 65536, admit: QueryFilter | None = None
    ) -> Subscription[Message]:
        """Receive what is published on matching keys; those ``admit`` refuses are dropped."""
        self._check_open()
        inbox: Inbox[Message] = Inbox(asyncio.get_running_loop(), buffer_size)
        entry = (key_expr, inbox if admit is None else Screened(inbox, admit))
        self.hub.subscribers.append(entry)

        def remove() -> None:
            with contextlib.suppress(ValueError):
                self.hub.subscribers.remove(entry)

        sub = Subscription(inbox, remove)
        self._subs.append(sub)
        return sub

    async def ask(self, key_expr: str, payload: bytes = b"", *, timeout: float) -> Replies:
        """Ask every matching queryable (concurrently); each reply as its handler returns.

        The query owns its handlers' tasks: those still running at ``timeout``, or when
        the caller leaves early, are cancelled, and `Replies.aclose` waits for them.
        """
        self._check_open()
        loop = asyncio.get_running_loop()
        inbox: Inbox[Reply] = Inbox(loop)
        targets = [
            (e, h)
            for e, h in self.hub.queryables
            if key_matches(e, key_expr) or key_matches(key_expr, e)
        ]
        if not targets:
            inbox.close()
            return Replies(inbox, _ignore)
        left = len(targets)

        def answered(expr: str, task: asyncio.Task[bytes | None]) -> None:
            nonlocal left
            left -= 1
            if not task.cancelled():
                if (exc := task.exception()) is not None:
                    inbox.put(Reply(expr, str(exc).encode(), ok=False))
                elif (r := task.result()) is not None:
                    inbox.put(Reply(expr, r))
            if not left:
                inbox.close()

        tasks = []
        for e, h in targets:
            task = loop.create_task(
                _ask(h, key_expr, payload), name=f"memory.query[{key_expr}].{e}"
            )
            task.add_done_callback(functools.partial(answered, e))
            tasks.append(task)

        def end() -> None:
            timer.cancel()
            for t in tasks:
                t.cancel()
            inbox.close()  # a reply not yet put when the query ends is late: dropped

        async def ended() -> None:
            await asyncio.wait(tasks)

        timer = loop.call_later(timeout, end)
        return Replies(inbox, end, ended)

    async def serve(
        self, key_expr: str, handler: QueryHandler, *, admit: QueryFilter | None = None
    ) -> Handle:
        """Answer queries on ``key_expr``; those ``admit`` refuses get no reply."""
        self._check_open()
        if admit is not None:
            answer = handler

            async def handler(key: str, payload: bytes) -> bytes | None:
                return await answer(key, payload) if admit(payload) else None

        entry = (key_expr, handler)
        self.hub.queryables.append(entry)

        def remove() -> None:
            with contextlib.suppress(ValueError):
                self.hub.queryables.remove(entry)

        h = Handle(remove)
        self._handles.append(h)
        return h

    async def declare_token(self, key: str) -> Handle:
        """Announce presence under ``key`` until closed."""
        self._check_open()
        if "*" in key:
            raise TransportError(f"a liveliness token needs a concrete key, not {key!r}")
        first = self.hub.tokens.get(key, 0) == 0
        self.hub.tokens[key] = self.hub.tokens.get(key, 0) + 1
        if first:
            self.hub._presence(key, True)

        def remove() -> None:
            n = self.hub.tokens.get(key, 0) - 1
            if n <= 0:
                self.hub.tokens.pop(key, None)
                self.hub._presence(key, False)
            else:
                self.hub.tokens[key] = n

        h = Handle(remove)
        self._handles.append(h)
        return h

    async def tokens(
        self, key_expr: str, *, timeout: float, keep: Callable[[str], bool] | None = None
    ) -> list[str]:
        """The tokens alive on ``key_expr`` that ``keep`` keeps (the hub knows them all)."""
        self._check_open()
        return sorted(
            key
            for key in self.hub.tokens
            if key_matches(key_expr, key) and (keep is None or keep(key))
        )

    async def watch_presence(
        self, key_expr: str, *, history: bool = True, buffer_size: int = 4096
    ) -> Subscription[Presence]:
        """Be told of tokens matching ``key_expr`` appearing and going."""
        self._check_open()
        inbox: Inbox[Presence] = Inbox(asyncio.get_running_loop(), buffer_size)
        if history:
            for key in sorted(self.hub.tokens):
                if key_matches(key_expr, key):
                    inbox.put(Presence(key, True))
        entry = (key_expr, inbox)
        self.hub.watchers.append(entry)

        def remove() -> None:
            with contextlib.suppress(ValueError):
                self.hub.watchers.remove(entry)

        sub = Subscription(inbox, remove)
        self._subs.append(sub)
        return sub
