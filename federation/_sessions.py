"""How the proxies seal and open batches: this platform's sessions with its peers.

Batches are sealed per receiver with the session the Interface Agents agreed
(`InterfaceSessions`); anything implementing `SessionsProvider` may stand in for it
(`TableSessions` over a bare `SessionTable`; `PlainSessions`, unauthenticated, for tests).
"""

from __future__ import annotations

import time
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import msgpack

from agents import (
    Malformed,
    Misdirected,
    SessionTable,
    Unencrypted,
    UnknownPlatform,
    UnknownSession,
    check_name,
)

if TYPE_CHECKING:
    from agents import InterfaceAgent

__all__ = ["InterfaceSessions", "PlainSessions", "SessionsProvider", "TableSessions"]

_packb = msgpack.packb
_unpackb = msgpack.unpackb


@runtime_checkable
class SessionsProvider(Protocol):
    """How the proxies seal and open batches: this platform's sessions with its peers."""

    async def ensure(self, peer: str) -> None:
        """Make sure there is a session to seal for ``peer`` (agree one if need be)."""
        ...

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        """Seal ``body`` for ``peer``; UnknownSession or Expired when one must be agreed."""
        ...

    def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
        """``(authenticated sender platform, body)``, or an AuthenticationError."""
        ...


class TableSessions:
    """Seals and opens with a `SessionTable`; ``agree(peer)``, if given, makes a session."""

    def __init__(
        self, table: SessionTable, agree: Callable[[str], Awaitable[None]] | None = None
    ) -> None:
        self.table = table
        self.agree = agree

    async def ensure(self, peer: str) -> None:
        """Agree a session with ``peer`` unless one can seal already."""
        if self.table.session_for(peer) is not None:
            return
        if self.agree is None:
            raise UnknownSession(f"no session with {peer!r}, and no way to agree one", peer)
        await self.agree(peer)

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        """Seal with the table's current session for ``peer``."""
        return self.table.seal_bytes(peer, body)

    def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
        """Open with the table."""
        return self.table.open_bytes(envelope)


class InterfaceSessions(TableSessions):
    """The sessions of a platform's Interface Agent: agreed, renewed and recovered by it."""

    def __init__(self, agent: InterfaceAgent, *, renew_check: float = 1.0) -> None:
        super().__init__(agent.sessions, agent.agree)
        self.agent = agent
        self.renew_check = renew_check
        self._checked: dict[str, float] = {}

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        """Seal for ``peer``; now and then, have the agent renew a session that asks for it."""
        envelope = self.table.seal_bytes(peer, body)
        now = time.monotonic()
        if now - self._checked.get(peer, -1e9) >= self.renew_check:
            # what the agent's own send does per message, here once a second: batches
            # come by the thousand and the session's age changes slowly
            self._checked[peer] = now
            self.agent.renew_if_needed(peer)
        return envelope

    def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
        """Open; a trusted peer sealing on a session we lost gets a new one agreed.

        What opens is shown to the owner while it watches; a plain envelope where
        encryption is required is audited (a misconfigured or downgrading peer).
        """
        try:
            frm, body = self.table.open_bytes(envelope)
        except UnknownSession as exc:
            if exc.platform is not None:
                self.agent.rehandshake(exc.platform)  # rate-limited by the agent
            raise
        except Unencrypted as exc:
            self.agent.audit_unauthenticated(
                exc.platform, f"{exc.code}: {exc.reason}", stage="stream"
            )
            raise
        if self.agent.mirroring:
            self.agent.mirror_bytes(frm, body)
        return frm, body


class PlainSessions:
    """No authentication at all: ``[1, from, to, body]``. For tests and local benchmarks only.

    ``trusted``, when given, is the set of senders accepted (others: UnknownPlatform).
    """

    def __init__(self, me: str, trusted: set[str] | None = None) -> None:
        self.me = check_name(me)
        self.trusted = trusted

    async def ensure(self, peer: str) -> None:
        """Nothing to agree."""

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        """Wrap ``body`` with sender and receiver."""
        envelope: bytes = _packb([1, self.me, peer, body])
        return envelope

    def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
        """Unwrap, checking the receiver and (when set) the trusted senders."""
        try:
            env = _unpackb(envelope, raw=False)
        except Exception as exc:
            raise Malformed(f"not msgpack: {exc}") from None
        if type(env) is not list or len(env) != 4 or env[0] != 1:
            raise Malformed("a plain envelope is [1, from, to, body]")
        _, frm, to, body = env
        if type(frm) is not str or type(to) is not str or type(body) is not bytes:
            raise Malformed("a plain envelope is [1, from, to, body]")
        if to != self.me:
            raise Misdirected(f"envelope for {to!r} reached {self.me!r}", frm)
        if self.trusted is not None and frm not in self.trusted:
            raise UnknownPlatform(f"platform {frm!r} is not trusted", frm)
        return frm, body
