"""The agent platform: hosts agents, delivers between them, and reaches other platforms.

Messages between agents of one platform are handed over as the validated `ACLMessage`
objects themselves (no JSON), through the same conversation and handler path as remote
ones. So treat a message, content included, as immutable: the receiver holds the very
object the sender built. (The 256 KiB limit is checked only where JSON is parsed.)

Messages for agents of other platforms go through a `RemoteChannel`, the one seam
between the platform and the network: `PlainChannel` (JSON, no authentication) for tests
and trusted single-host setups; the Interface Agent (signed sessions) is the other one.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, Self, TypeVar, runtime_checkable

import orjson

from ._acl import MAX_MESSAGE_BYTES, WIRE_VERSION, ACLMessage, Performative, name_of, platform_of
from ._agent import NEVER_ANSWERED, Agent
from ._aio import KeepCancelled
from ._dfgate import DEFAULT_DF_EVENT_LIMIT, DfEventLimit
from ._directory_auth import DirectoryAuth
from ._exceptions import AgentError, MessageError
from ._quote import quoted
from ._records import Record
from ._tally import Tally, since
from .transports import Handle, Message, Subscription, Transport

if TYPE_CHECKING:
    from ._df import DirectoryFacilitator, GlobalDirectory

log = logging.getLogger(__name__)

A = TypeVar("A", bound=Agent)

_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")

# A sender in a tight loop lets this process's other tasks run once per this many
# messages sent to other platforms (a power of two: a mask tests it). As many as a batch
# of ACL messages holds at most (the Interface Agent's MAX_BATCH): a turn of the loop
# fills one envelope, where a turn per 64 sealed and put four times as many.
_YIELD_MASK = 255


def wire_key(federation: str, kind: str, platform: str) -> str:
    """The key ``dyknow/<federation>/v1/<kind>/<platform>`` (``platform`` may be ``*``)."""
    return f"dyknow/{federation}/v{WIRE_VERSION}/{kind}/{platform}"


@runtime_checkable
class RemoteChannel(Protocol):
    """The seam between a platform and other platforms: how ACL messages leave and arrive.

    The platform calls, in this order:

    * ``await start(platform)`` once, while the platform opens (its task group is up,
      its agents are not started yet). The channel subscribes the platform's inbox
      ``platform.key("acl")`` (``dyknow/<fed>/v1/acl/<platform>``), runs its receive
      loop(s) as tasks owned by the platform (`AgentPlatform.spawn`) and returns once it
      receives. For each message that arrives and passes the channel's checks it calls
      ``await platform.deliver(message)``; for bytes that do not decode it calls
      ``await platform.reject(payload, reason)`` (logged, counted, and answered with
      not-understood when a sender can be told) or, when the sender cannot be trusted,
      drops them itself. Its receive loop never raises.
    * ``await send(platform_name, message)`` for each other platform that a message's
      receivers live on (one call per platform, whatever the number of receivers
      there). The channel serializes (and protects) the message and publishes it on
      ``platform.key("acl", platform_name)``; failures raise `TransportError`.
      A channel that batches what is sent in one turn of the loop may also have a plain
      method ``join_batch(platform_name, message) -> bool``, which the platform calls
      first for a message to one receiver: True when it took the message as ``send``
      would have (no coroutine per message in a burst), False when ``send`` must;
      likewise ``send_now(platform_name, message) -> bool``, called next: True when it
      sent the message as ``send`` would have without waiting for anything, False (and
      nothing sent) when ``send`` must. It
      may also have ``sends_now(platform_name) -> bool``: True when ``send`` would wait
      for nothing (no key exchange first, a transport that publishes at once), so a
      caller sending to many platforms can send to those in turn rather than each in a
      task of its own.
    * ``await aclose()`` once, as the platform closes: stop receiving. Idempotent.

    A channel never changes a message; what it refuses never reaches an agent.
    """

    async def start(self, platform: AgentPlatform) -> None:
        """Begin receiving for ``platform`` (see the class docstring)."""
        ...

    async def send(self, platform: str, message: ACLMessage) -> None:
        """Deliver ``message`` to the agents of the other platform ``platform``."""
        ...

    async def aclose(self) -> None:
        """Stop receiving."""
        ...


class PlainChannel:
    """ACL messages as plain JSON over the transport. NO AUTHENTICATION.

    Anyone who can publish on the transport can send as any agent of any platform. For
    tests and trusted single-host setups only; across hosts use the Interface Agent.
    """

    def __init__(self, *, max_bytes: int = MAX_MESSAGE_BYTES) -> None:
        self.max_bytes = max_bytes
        self._platform: AgentPlatform | None = None
        self._sub: Subscription[Message] | None = None

    async def start(self, platform: AgentPlatform) -> None:
        """Subscribe the platform's inbox and start the receive loop."""
        self._platform = platform
        log.info(
            "platform[%s]: plain channel: messages between platforms are NOT authenticated",
            platform.name,
        )
        self._sub = await platform.transport.subscribe(platform.key("acl"))
        platform.spawn(self._receive(self._sub), "acl-inbox")

    def sends_now(self, platform: str) -> bool:
        """Whether `send` waits for nothing: started, on a transport that publishes at once."""
        host = self._platform
        return host is not None and host.transport.publishes_nowait

    async def send(self, platform: str, message: ACLMessage) -> None:
        """Publish ``message`` as JSON on ``platform``'s inbox."""
        if self._platform is None:
            raise AgentError("channel not started")
        await self._platform.transport.publish(
            self._platform.key("acl", platform), message.to_json()
        )

    async def aclose(self) -> None:
        """Close the inbox subscription."""
        if self._sub is not None:
            self._sub.close()

    async def _receive(self, sub: Subscription[Message]) -> None:
        platform = self._platform
        assert platform is not None
        from_json = ACLMessage.from_json
        async for item in sub:
            try:
                message = from_json(item.payload, max_bytes=self.max_bytes)
            except MessageError as exc:
                await platform.reject(item.payload, exc.reason)
                continue
            try:
                await platform.deliver(message)
            except Exception:
                log.exception(
                    "platform[%s]: delivering %s failed", platform.name, message.performative
                )
        log.debug("platform[%s]: ACL inbox closed", platform.name)
        platform._inbox_ended(sub)


@dataclass(init=False, repr=False, eq=False)
class SenderStats(Record):
    """What one other (authenticated) platform sent here, as its channel's rate limit saw it.

    ``accepted``: messages that passed the rate limit (they then go through access control);
    ``limited``: messages dropped by it, of which ``refused`` were answered with ``refuse``.
    """

    __slots__ = ("accepted", "limited", "refused")
    accepted: int
    limited: int
    refused: int

    def __init__(self, accepted: int = 0, limited: int = 0, refused: int = 0) -> None:
        self.accepted = accepted
        self.limited = limited
        self.refused = refused


@dataclass(init=False, repr=False, eq=False)
class PlatformStats(Record):
    """What a platform has moved: local and remote deliveries, malformed input, drops.

    ``answers_dropped`` counts failure/not-understood answers to other platforms not sent
    because too many were on their way; ``unauthenticated`` envelopes that did not open
    (the Interface Agent drops them); ``rate_limited`` messages dropped by a sender's rate
    limit; ``kx_shed`` key-exchange requests dropped before their signature check (the
    Interface Agent's gate); ``kx_replies_refused`` replies to this platform's own
    key-exchange requests that it refused (junk, forged, …: anyone may answer them);
    ``kx_requests_refused`` key-exchange requests the gate let through whose checks
    (signature, freshness, trust) then refused them;
    ``denied`` authenticated messages the Interface Agent refused or dropped for what they
    claim or ask (a sender of another platform, no receiver here, a ``reply_to`` it does not
    allow, access denied; each audited), and those an agent refuses as the Interface Agent
    would have, had it seen the agent's service as it is now (the Gateway Agent, made
    private while they waited; also in ``agent_refused``); ``agent_refused`` requests this
    platform's agents answered with ``refuse`` themselves (a responder raising ``Refuse``);
    ``unknown_receiver`` / ``mailbox_full`` / ``stopping`` messages for no agent here / for
    a full mailbox / for an agent that is stopping (answered with ``failure``); those of
    other platforms among these four are audited summed up (``agent-refuse`` / ``delivery``
    records, one per platform and kind per `REFUSAL_AUDIT_INTERVAL`; docs/security.md);
    ``rehandshakes`` new sessions started because a trusted peer
    sealed on one this platform does not hold, ``rehandshakes_suppressed`` such cues
    ignored (at most one per peer per ``rehandshake_interval``), ``presence_suppressed``
    presence changes of trusted peers not acted on (over a peer's budget: presence is not
    authenticated, and each change acted on costs a key exchange); ``from_left``
    requests refused because their platform said, signed, that it left (also in
    ``denied``; served again once its signed directory snapshot lists it);
    ``declarations_lost`` what the platform declared on its transport (its liveliness
    token, its directory's queryable, …) that the transport ended by itself
    (`AgentPlatform.lost`); ``senders`` holds
    per-platform figures (keyed by authenticated platform name, so bounded by the trust
    file).
    """

    __slots__ = (
        "agent_refused",
        "answers_dropped",
        "declarations_lost",
        "denied",
        "forged",
        "from_left",
        "kx_replies_refused",
        "kx_requests_refused",
        "kx_shed",
        "local",
        "mailbox_full",
        "malformed",
        "misrouted",
        "presence_suppressed",
        "rate_limited",
        "received_remote",
        "rehandshakes",
        "rehandshakes_suppressed",
        "senders",
        "sent_remote",
        "stopping",
        "unauthenticated",
        "unknown_receiver",
    )
    local: int
    sent_remote: int
    received_remote: int
    malformed: int
    forged: int
    unknown_receiver: int
    mailbox_full: int
    stopping: int
    misrouted: int
    answers_dropped: int
    unauthenticated: int
    rate_limited: int
    kx_shed: int
    kx_replies_refused: int
    kx_requests_refused: int
    denied: int
    agent_refused: int
    rehandshakes: int
    rehandshakes_suppressed: int
    presence_suppressed: int
    from_left: int
    declarations_lost: int
    senders: dict[str, SenderStats]

    def __init__(
        self,
        local: int = 0,
        sent_remote: int = 0,
        received_remote: int = 0,
        malformed: int = 0,
        forged: int = 0,
        unknown_receiver: int = 0,
        mailbox_full: int = 0,
        stopping: int = 0,
        misrouted: int = 0,
        answers_dropped: int = 0,
        unauthenticated: int = 0,
        rate_limited: int = 0,
        kx_shed: int = 0,
        kx_replies_refused: int = 0,
        kx_requests_refused: int = 0,
        denied: int = 0,
        agent_refused: int = 0,
        rehandshakes: int = 0,
        rehandshakes_suppressed: int = 0,
        presence_suppressed: int = 0,
        from_left: int = 0,
        declarations_lost: int = 0,
        senders: dict[str, SenderStats] | None = None,
    ) -> None:
        self.local = local
        self.sent_remote = sent_remote
        self.received_remote = received_remote
        self.malformed = malformed
        self.forged = forged
        self.unknown_receiver = unknown_receiver
        self.mailbox_full = mailbox_full
        self.stopping = stopping
        self.misrouted = misrouted
        self.answers_dropped = answers_dropped
        self.unauthenticated = unauthenticated
        self.rate_limited = rate_limited
        self.kx_shed = kx_shed
        self.kx_replies_refused = kx_replies_refused
        self.kx_requests_refused = kx_requests_refused
        self.denied = denied
        self.agent_refused = agent_refused
        self.rehandshakes = rehandshakes
        self.rehandshakes_suppressed = rehandshakes_suppressed
        self.presence_suppressed = presence_suppressed
        self.from_left = from_left
        self.declarations_lost = declarations_lost
        self.senders = {} if senders is None else senders


_UNOPENED, _OPENED, _CLOSING, _CLOSED = "unopened", "opened", "closing", "closed"

# remote answers (failure, not-understood) the platform sends in the background at once
MAX_ANSWERING = 256

REFUSAL_AUDIT_INTERVAL = 1.0
"""Seconds between two audit records summing up one platform's refusals of one kind."""

REFUSALS_ONE_BY_ONE = 10
"""Refusals of what a platform asks (`AgentPlatform.audit_refused`) audited one by one per
platform per `REFUSAL_AUDIT_INTERVAL`; the rest of that interval are summed up."""

# platforms whose one-by-one budget is kept at once (members: the trust file bounds them);
# past it, the budgets whose interval is over are forgotten
_BUDGETS_KEPT = 1024

# audit record (verdict, stage, what) per kind of refusal summed up by `_refusals`
_REFUSAL_KINDS = {
    "refuse": ("refused", "agent-refuse", "request(s) answered with refuse by an agent"),
    "unknown-receiver": ("dropped", "delivery", "message(s) for no agent of this platform"),
    "mailbox-full": ("dropped", "delivery", "message(s) for an agent whose mailbox is full"),
    "stopping": ("dropped", "delivery", "message(s) for an agent that is stopping"),
    "unsolicited": (
        "dropped",
        "delivery",
        "failure / not-understood message(s) in no conversation of the agent",
    ),
    "not-understood": (
        "dropped",
        "delivery",
        "message(s) no handler of the agent takes (answered not-understood)",
    ),
    # more (platform, kind) pairs in one interval than the tally sums up one by one
    "*": ("dropped", "delivery", "refusal(s) of any kind (too many platforms to tell apart)"),
}


class AgentPlatform:
    """Hosts agents under one platform name; an async context manager that cannot reopen.

    Entering starts the remote channel, the Directory Facilitator (``df@<name>``) and the
    global directory view, then declares the liveliness token
    ``dyknow/<federation>/v1/alive/<name>``; leaving undoes all of it and stops every
    agent. The transport is the caller's: open it before, close it after.
    ``df_event_limit`` is the global directory's shedding of directory events
    (`DfEventLimit`; None: none).
    """

    def __init__(
        self,
        name: str,
        transport: Transport,
        *,
        federation: str = "default",
        channel: RemoteChannel | None = None,
        directory: bool = True,
        global_directory: bool = True,
        query_timeout: float = 1.0,
        df_event_limit: DfEventLimit | None = DEFAULT_DF_EVENT_LIMIT,
    ) -> None:
        for what, value in (("platform", name), ("federation", federation)):
            if not _NAME.fullmatch(value):
                raise ValueError(f"{what} name {value!r}: use letters, digits, '-', '_', '.'")
        self.name = name
        self.federation = federation
        self.transport = transport
        self.channel: RemoteChannel = channel if channel is not None else PlainChannel()
        self.query_timeout = query_timeout
        # the global directory's shedding of df-events (`GlobalDirectory`; None: none)
        self.df_event_limit = df_event_limit
        # a channel that batches a burst can take a message into the current batch
        # without a coroutine (`InterfaceAgent.join_batch`)
        self._join_batch: Callable[[str, ACLMessage], bool] | None = getattr(
            self.channel, "join_batch", None
        )
        # the last single receiver `send` met and its platform
        self._last_receiver: str | None = None
        self._last_target = ""
        # and send one that waits for nothing without one (`InterfaceAgent.send_now`)
        self._send_now: Callable[[str, ACLMessage], bool] | None = getattr(
            self.channel, "send_now", None
        )
        # Signs this platform's directory statements and checks others' (with the
        # channel's key pair and trust file, when it has them: docs/security.md).
        policy = getattr(self.channel, "policy", None)
        self.directory_auth = DirectoryAuth(
            federation,
            getattr(self.channel, "keys", None),
            getattr(self.channel, "trust", None),
            skew=getattr(policy, "skew", 30.0),  # the channel's, as for its envelopes
        )
        self.stats = PlatformStats()
        self.df: DirectoryFacilitator | None = None
        self.global_df: GlobalDirectory | None = None
        self._want_df = directory
        self._want_global = global_directory and directory
        self._agents: dict[str, Agent] = {}
        # agents whose add was cancelled, unlisted but still in their setup or teardown:
        # the close must reach them too (a setup waiting forever would hold it)
        self._given_up: set[Agent] = set()
        self._state = _UNOPENED
        self._tg: asyncio.TaskGroup | None = None
        self._stack: contextlib.AsyncExitStack | None = None  # holds the entered task group
        self._tasks: set[asyncio.Task[Any]] = set()
        self._token: Handle | None = None
        # what the transport ended by itself, by what it was: why (`declared`)
        self.lost: dict[str, str] = {}
        self._on_lost: list[Callable[[str, str], None]] = []
        self._lock = asyncio.Lock()
        self._answering = 0  # answers of the platform's own being sent in the background
        # refusals of other platforms' messages past the channel (an agent's refuse, no
        # such receiver, a full mailbox): summed up per (platform, kind) per second
        self._refusals = Tally(self._audit_refusals, interval=REFUSAL_AUDIT_INTERVAL)
        # per platform: [start of its budget's interval (loop time), records written in it]
        self._one_by_one: dict[str, list[float]] = {}

    def __repr__(self) -> str:
        return f"<AgentPlatform {self.name} ({self.federation}) {self._state}>"

    def key(self, kind: str, platform: str | None = None) -> str:
        """This federation's key of ``kind`` for ``platform`` (default: this one)."""
        return wire_key(self.federation, kind, platform or self.name)

    def audit(self, **fields: Any) -> None:
        """Add a record to the channel's audit log (an agent's refusal of another platform).

        The Interface Agent audits what it admits or refuses; an agent that then refuses an
        admitted request for what it asks (a sharing rule, a limit) records it here, so
        the audit shows the refusal too. A channel without an audit log ignores it.
        """
        log_ = getattr(self.channel, "audit", None)
        if log_ is not None:
            log_.record(**fields)

    def declared(self, handle: Handle, what: str, meaning: str) -> Handle:
        """``handle``, the platform told if the transport ends it by itself; returned.

        ``what`` names it ("directory queryable dyknow/…/df/uav-a"), ``meaning`` says what
        its loss means for others ("other platforms can no longer find this platform's
        agents"). An end is logged at ERROR with both and the transport's reason,
        counted (``stats.declarations_lost``), kept in `lost` and passed to the
        `on_lost` callbacks. A close is no end, nor one once the platform closes.
        """
        handle.on_end(lambda reason: self._lose(what, meaning, reason))
        return handle

    def _inbox_ended(self, sub: Subscription[Any]) -> None:
        """The channel's inbox ``sub`` ended: lost (as `declared`) unless closed, or closing."""
        self.ended(
            sub,
            f"inbox subscription {self.key('acl')}",
            "other platforms' messages to this platform's agents are no longer received",
        )

    def ended(self, sub: Subscription[Any], what: str, meaning: str) -> None:
        """``sub``, which its consumer read to its end, lost (as `declared`) unless closed,
        or the platform closing: its consumer's call once its loop is over.

        A subscription has no reason to give: the transport's own warning before says why
        (MQTT: the broker refused its filter after a reconnection).
        """
        # (a test's inbox may be any async iterable: no transport ends it)
        if isinstance(sub, Subscription) and not sub.closed and self._state == _OPENED:
            self._lose(what, meaning, "the transport ended the subscription")

    def on_lost(self, callback: Callable[[str, str], None]) -> None:
        """Have ``callback(what, reason)`` called for each declaration the transport ends.

        At once for each lost already (`lost`), then as they are lost.
        """
        for what, reason in list(self.lost.items()):
            callback(what, reason)
        self._on_lost.append(callback)

    def _lose(self, what: str, meaning: str, reason: str) -> None:
        """The transport ended ``what`` by itself: logged, counted, the callbacks told.

        Once the platform closes, no loss: its close undeclares everything anyway.
        """
        if self._state != _OPENED:
            log.debug("platform[%s]: closing, its %s ended (%s)", self.name, what, reason)
            return
        self.stats.declarations_lost += 1
        self.lost[what] = reason
        log.error("platform[%s]: lost its %s (%s): %s", self.name, what, reason, meaning)
        for callback in list(self._on_lost):
            try:
                callback(what, reason)
            except Exception:  # one listener's bug must not keep the others untold
                log.exception("platform[%s]: a callback told of a lost %s raised", self.name, what)

    # -- lifecycle --------------------------------------------------------------------

    async def __aenter__(self) -> Self:
        if self._lock.locked() or self._state != _UNOPENED:
            raise AgentError(f"platform {self.name} is {self._state}; it cannot reopen")
        async with self._lock:
            stack = self._stack = contextlib.AsyncExitStack()
            self._tg = await stack.enter_async_context(asyncio.TaskGroup())
            self._state = _OPENED
            try:
                await self._open()
            except BaseException:
                try:
                    await self._shutdown()
                finally:
                    self._cancel_everything()
                    await stack.aclose()
                raise
        return self

    async def _open(self) -> None:
        from ._df import DirectoryFacilitator, GlobalDirectory

        await self.channel.start(self)
        if self._want_df:
            self.df = await self.add(DirectoryFacilitator())
        if self._want_global:
            self.global_df = GlobalDirectory(
                self, query_timeout=self.query_timeout, event_limit=self.df_event_limit
            )
            await self.global_df.start()
        # Last: when others see us alive, our inbox and directory already answer.
        key = self.key("alive")
        self._token = self.declared(
            await self.transport.declare_token(key),
            f"liveliness token {key}",
            "other platforms see this platform gone: they drop its agents from their "
            "directories and can no longer reach them",
        )

    async def __aexit__(self, et: Any, ev: Any, tb: Any) -> None:
        if self._state != _OPENED:
            return
        stack = self._stack
        assert stack is not None
        try:
            await self._shutdown()
        finally:
            # Normally every task is stopped by now; if the shutdown itself was cut short
            # (cancelled), this ends the rest so the group does not wait forever. Not
            # passing the body's error on (aclose passes none) keeps it as it is: the
            # group would wrap it.
            self._cancel_everything()
            # a task that lost its cancellation would hold the group's close forever
            again = KeepCancelled(self._outliving)
            try:
                await stack.aclose()
            finally:
                again.stop()

    def _outliving(self) -> list[asyncio.Task[Any]]:
        """The platform's tasks, its agents' and theirs: what its close cancels."""
        tasks = list(self._tasks)
        for agent in [*self._agents.values(), *self._given_up]:
            if agent._task is not None:
                tasks.append(agent._task)
            tasks.extend(agent._children)
        return tasks

    async def _shutdown(self) -> None:
        self._state = _CLOSING
        if self.df is not None and self._token is not None:
            try:  # signed, so others believe it at once (a cleared presence alone may be forged)
                async with asyncio.timeout(self.query_timeout):
                    await self.df.announce_leave()
            except Exception as exc:  # the transport may be gone already
                log.debug("platform[%s]: announcing the leave: %s", self.name, exc)
        if self._token is not None:
            try:
                await self._token.aclose()
            except Exception as exc:  # the transport may be gone already
                log.debug("platform[%s]: undeclaring the token: %s", self.name, exc)
        # Users' agents first, newest first; the directory last: they deregister from it.
        agents = [a for a in reversed(self._agents.values()) if a is not self.df]
        # one given up past its setup finishes its teardown; one still in it is cancelled
        agents += [a for a in self._given_up if a.running]
        for agent in [*agents, *([self.df] if self.df is not None else [])]:
            await agent.stop()
        if self.global_df is not None:
            self.global_df.close()
        # refusals counted since the last summary are written before the audit closes (the
        # channel's subscriptions close with it, so none comes once it closes; any later
        # is counted in the stats only)
        self._refusals.close()
        try:
            await self.channel.aclose()
        except Exception:
            log.exception("platform[%s]: closing the channel failed", self.name)
        for task in list(self._tasks):
            task.cancel()
        self._state = _CLOSED

    def _cancel_everything(self) -> None:
        for agent in [*self._agents.values(), *self._given_up]:
            if agent._task is not None:
                agent._task.cancel()
        for task in list(self._tasks):
            task.cancel()
        if self.global_df is not None:
            self.global_df.close()
        self._state = _CLOSED

    @property
    def running(self) -> bool:
        """Whether the platform is open."""
        return self._state == _OPENED

    def spawn(self, coro: Coroutine[Any, Any, Any], name: str) -> asyncio.Task[Any]:
        """Run ``coro`` as a task owned by the platform (``platform[p].<name>``); errors logged."""
        if self._tg is None or self._state not in (_OPENED,):
            coro.close()
            raise AgentError(f"platform {self.name} is {self._state}")
        task = self._tg.create_task(self._guard(coro, name), name=f"platform[{self.name}].{name}")
        # cancelled before its first step (a start given up), the guard never awaits
        # ``coro``: close it then
        task.add_done_callback(lambda _: coro.close())
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    async def _guard(self, coro: Coroutine[Any, Any, Any], name: str) -> None:
        try:
            await coro
        except Exception:
            log.exception("platform[%s]: task %s failed", self.name, name)

    # -- agents -----------------------------------------------------------------------

    async def add(self, agent: A) -> A:
        """Start ``agent`` on this platform; returns it once it is ready (its setup ran)."""
        if self._state != _OPENED or self._tg is None:
            raise AgentError(f"platform {self.name} is {self._state}")
        if agent.name in self._agents:
            raise AgentError(f"platform {self.name} already has an agent named {agent.name!r}")
        self._agents[agent.name] = agent
        try:
            await agent._start(self, self._tg)
        except BaseException:
            self._agents.pop(agent.name, None)
            if agent._platform is self and agent._task is not None and not agent._task.done():
                self._given_up.add(agent)  # it stops on its own; the close ends it if not
            raise
        return agent

    async def remove(self, agent: Agent | str) -> None:
        """Stop an agent (by object or name) and deregister its services."""
        found = self._agents.get(agent if isinstance(agent, str) else agent.name)
        if found is not None:
            await found.stop()

    def _forget(self, agent: Agent) -> None:
        """Called by an agent as it stops."""
        if self._agents.get(agent.name) is agent:
            del self._agents[agent.name]
        self._given_up.discard(agent)
        if self.df is not None and agent is not self.df and self.df.running:
            self.df.forget_agent(agent.aid)

    def agent(self, name: str) -> Agent | None:
        """The running agent called ``name`` (without ``@platform``), if any."""
        return self._agents.get(name)

    @property
    def agents(self) -> list[Agent]:
        """The agents running here."""
        return list(self._agents.values())

    # -- messages ---------------------------------------------------------------------

    async def send(self, message: ACLMessage) -> None:
        """Deliver to local receivers directly, and once per other platform through the channel."""
        if self._state not in (_OPENED, _CLOSING):
            raise AgentError(f"platform {self.name} is {self._state}")
        receivers = message.receivers
        if len(receivers) == 1:  # the common case, without building sets
            receiver = receivers[0]
            # platform_of, remembered for the last receiver: a burst repeats one (a str,
            # immutable: the same object has the same platform)
            if receiver is self._last_receiver:
                target = self._last_target
            else:
                target = receiver.rpartition("@")[2]
                self._last_receiver, self._last_target = receiver, target
            if target == self.name:
                await self._local(receiver, message)
                return
            # what _remote does, inline: a coroutine less per message sent in a burst
            join = self._join_batch
            if join is None or not join(target, message):
                now = self._send_now
                if now is None or not now(target, message):
                    await self.channel.send(target, message)
            stats = self.stats
            stats.sent_remote += 1
            if not stats.sent_remote & _YIELD_MASK:
                await asyncio.sleep(0)  # as in _remote: let this process's receivers run
            return
        remote: dict[str, None] = {}
        for receiver in receivers:
            target = platform_of(receiver)
            if target == self.name:
                await self._local(receiver, message)
            else:
                remote[target] = None
        for target in remote:
            await self._remote(target, message)

    async def _remote(self, target: str, message: ACLMessage) -> None:
        await self.channel.send(target, message)
        self.stats.sent_remote += 1
        if not self.stats.sent_remote & _YIELD_MASK:
            # Publishing rarely suspends: a sender in a tight loop would starve this
            # process's receive loops (and fill the receiver's inbox) without this.
            await asyncio.sleep(0)

    async def deliver(self, message: ACLMessage) -> None:
        """Hand a message that came from another platform to its receivers on this one.

        A message claiming a sender of this platform is dropped: local messages never
        travel through a channel, so it is forged.
        """
        self.stats.received_remote += 1
        if platform_of(message.sender) == self.name:
            self.stats.forged += 1
            log.warning(
                "platform[%s]: dropped a message from outside claiming to be from %s",
                self.name,
                message.sender,
            )
            return
        local = False
        for receiver in message.receivers:
            if platform_of(receiver) == self.name:
                local = True
                await self._local(receiver, message)
        if not local:
            self.stats.misrouted += 1
            log.warning("platform[%s]: message for %s arrived here", self.name, message.receivers)

    def _ready_receiver(self, message: ACLMessage) -> Agent | None:
        """The one local agent a remote ``message`` can be handed to now, without waiting.

        None unless `deliver` would hand it over at once: one receiver, running, its
        mailbox less than half full, and the sender not claiming this platform. Changes
        nothing: the caller then calls `_deliver_now`, or `deliver` for the general path.
        """
        receivers = message.receivers
        if len(receivers) != 1:
            return None
        receiver = receivers[0]
        name = self.name
        if platform_of(receiver) != name or platform_of(message.sender) == name:
            return None
        agent = self._agents.get(name_of(receiver))
        if agent is None or not agent.running:
            return None
        mailbox = agent._mailbox
        return agent if len(mailbox) < mailbox.maxlen >> 1 else None

    def _deliver_now(self, agent: Agent, message: ACLMessage) -> None:
        """What `deliver` does for a message `_ready_receiver` chose ``agent`` for."""
        stats = self.stats
        stats.received_remote += 1
        agent._deliver(message)  # running, room in its mailbox: taken
        stats.local += 1

    async def _local(self, receiver: str, message: ACLMessage) -> None:
        agent = self._agents.get(name_of(receiver))
        if agent is not None and agent._deliver(message):
            self.stats.local += 1
            mailbox = agent._mailbox
            if len(mailbox) > mailbox.maxlen >> 1:
                # A sender in a tight loop (or a channel draining a burst) never yields:
                # give the receiver its turn before its mailbox overflows.
                await asyncio.sleep(0)
            return
        if agent is None:
            self.stats.unknown_receiver += 1
            kind, reason = "unknown-receiver", f"no agent {receiver}"
        elif not agent.running:
            self.stats.stopping += 1
            kind, reason = "stopping", f"{receiver} is stopping"
        else:
            self.stats.mailbox_full += 1
            kind, reason = "mailbox-full", f"the mailbox of {receiver} is full"
            if self.stats.mailbox_full == 1 or self.stats.mailbox_full % 1000 == 0:
                log.warning(
                    "platform[%s]: %s (%d dropped)", self.name, reason, self.stats.mailbox_full
                )
        peer = platform_of(message.sender)
        if peer != self.name:  # another platform's (authenticated by the channel)
            self._refusals.add((peer, kind), reason)
        if message.performative not in NEVER_ANSWERED:
            # The platform answers for the receiver: it is authoritative for its names.
            try:
                answer = message.reply(Performative.FAILURE, reason, sender=receiver)
            except Exception:
                log.exception("platform[%s]: could not tell %s", self.name, message.sender)
            else:
                await self._answer(answer)

    def agent_refused(self, message: ACLMessage, reason: object) -> None:
        """Count a ``refuse`` an agent here answers ``message`` with; audit it (summed up)."""
        self.stats.agent_refused += 1
        peer = platform_of(message.sender)
        if peer != self.name:
            # the reason may echo what the asker sent (a conversation id, a label): on one
            # line, bounded (`quoted`)
            detail = f"{', '.join(message.receivers)}: {quoted(reason)}"
            self._refusals.add((peer, "refuse"), detail)

    def agent_dropped(self, message: ACLMessage, kind: str, detail: str) -> None:
        """Audit (summed up) a message of another platform an agent here had no use for.

        ``kind``: ``unsolicited`` (an answer in no conversation: dropped) or
        ``not-understood`` (no handler: answered not-understood); the agent counts it.
        """
        peer = platform_of(message.sender)
        if peer != self.name:
            self._refusals.add((peer, kind), detail)

    def audit_refused(self, message: ACLMessage, stage: str, code: str, reason: str) -> bool:
        """Audit a request another platform's agent made and an agent here refused for what
        it asks (a label not here, a sharing rule, a limit): one by one within that
        platform's budget (`REFUSALS_ONE_BY_ONE` per `REFUSAL_AUDIT_INTERVAL`), the rest
        summed up per platform, stage and code. True when written one by one.

        A member may repeat such a request at its rate limit: a record each would rotate
        the audit file's history away in seconds. This platform's own agents' refusals
        are always written one by one. On the event loop.
        """
        peer = platform_of(message.sender)
        if peer != self.name and not self._within_budget(peer):
            self._refusals.add((peer, stage, code), quoted(reason))
            return False
        self.audit(
            verdict="refused",
            stage=stage,
            code=code,
            **{"from": peer},
            sender=message.sender,
            receivers=message.receivers,
            performative=message.performative.value,
            conversation_id=message.conversation_id,
            reason=f"{code}: {reason}",
        )
        return True

    def _within_budget(self, peer: str) -> bool:
        """Whether ``peer``'s refusal is written one by one (and counted in its budget)."""
        now = asyncio.get_running_loop().time()
        budgets = self._one_by_one
        budget = budgets.get(peer)
        if budget is None or now - budget[0] >= REFUSAL_AUDIT_INTERVAL:
            if budget is None and len(budgets) >= _BUDGETS_KEPT:
                for p in [p for p, b in budgets.items() if now - b[0] >= REFUSAL_AUDIT_INTERVAL]:
                    del budgets[p]
            budget = budgets[peer] = [now, 0]
        if budget[1] >= REFUSALS_ONE_BY_ONE:
            return False
        budget[1] += 1
        return True

    def _audit_refusals(self, key: object, count: int, detail: str, seconds: float | None) -> None:
        """One audit record for ``count`` refusals of one platform's messages, of one kind."""
        if isinstance(key, tuple) and len(key) == 3:  # `audit_refused`'s, past the budget
            peer, stage, code = key
            self.audit(
                verdict="refused",
                stage=stage,
                code=code,
                count=count,
                **{"from": peer},
                reason=(
                    f"{code}: {count} more request(s) refused without a record each (over "
                    f"{REFUSALS_ONE_BY_ONE} per {REFUSAL_AUDIT_INTERVAL:g} s of one platform), "
                    f"from {peer!r}{since(seconds)} (last: {detail})"
                ),
            )
            return
        peer, kind = key if isinstance(key, tuple) else ("*", "*")
        verdict, stage, what = _REFUSAL_KINDS[kind]
        self.audit(
            verdict=verdict,
            stage=stage,
            code=kind,
            count=count,
            **{"from": peer},
            reason=f"{kind}: {count} {what}, from {peer!r}{since(seconds)} (last: {detail})",
        )

    async def reject(self, payload: bytes, reason: str) -> bool:
        """Account for bytes that arrived but are not a valid message (never raises).

        Logged and counted; when the sender can be read from them, it gets a
        ``not-understood`` saying why. True when such an answer was made.
        """
        self.stats.malformed += 1
        n = self.stats.malformed
        level = logging.WARNING if n <= 10 or n % 1000 == 0 else logging.DEBUG
        log.log(level, "platform[%s]: malformed message #%d: %s", self.name, n, reason)
        try:
            answer = self._not_understood(payload, reason)
        except Exception:
            log.exception("platform[%s]: could not answer a malformed message", self.name)
            return False
        if answer is None:
            return False
        await self._answer(answer)
        return True

    async def _answer(self, answer: ACLMessage) -> None:
        """Send an answer the platform gives itself (failure, not-understood); never raises.

        The caller is often a channel's receive loop. Sending to another platform may wait
        for a key exchange (seconds, when that platform does not answer, and a message's
        ``reply_to`` chooses it), so remote answers go out in the background, at most
        ``MAX_ANSWERING`` at a time; beyond that they are dropped and counted
        (``stats.answers_dropped``): a flood of such messages cannot pile up tasks.
        """
        name = self.name
        if self._state != _OPENED or all(platform_of(r) == name for r in answer.receivers):
            # local (no network wait), or closing (no more tasks): as before, in line
            try:
                await self.send(answer)
            except Exception:
                log.exception("platform[%s]: could not send %s", name, answer.performative)
            return
        if self._answering >= MAX_ANSWERING:
            self.stats.answers_dropped += 1
            n = self.stats.answers_dropped
            level = logging.WARNING if n <= 10 or n % 1000 == 0 else logging.DEBUG
            log.log(
                level,
                "platform[%s]: %s to %s dropped (#%d)",
                name,
                answer.performative,
                answer.receivers,
                n,
            )
            return
        self._answering += 1
        try:
            self.spawn(self._send_answer(answer), "answer")
        except BaseException:
            self._answering -= 1
            raise

    async def _send_answer(self, answer: ACLMessage) -> None:
        try:
            await self.send(answer)
        except Exception as exc:
            log.warning(
                "platform[%s]: could not send %s to %s: %s",
                self.name,
                answer.performative,
                answer.receivers,
                exc,
            )
        finally:
            self._answering -= 1

    def _not_understood(self, payload: bytes, reason: str) -> ACLMessage | None:
        if len(payload) > 4 * MAX_MESSAGE_BYTES:
            return None  # not worth parsing to find whom to tell
        try:
            obj = orjson.loads(payload)
        except orjson.JSONDecodeError:
            return None
        if not isinstance(obj, dict):
            return None
        sender = obj.get("sender")
        if not isinstance(sender, str) or platform_of(sender) == self.name:
            return None  # no one to tell, or a local sender forged from outside
        performative = obj.get("performative")
        if isinstance(performative, str) and performative in NEVER_ANSWERED:
            return None
        me = f"ams@{self.name}"
        receivers = obj.get("receivers")
        if isinstance(receivers, list):
            for r in receivers:
                if (
                    isinstance(r, str)
                    and platform_of(r) == self.name
                    and name_of(r) in self._agents
                ):
                    me = r
                    break
        fields: dict[str, Any] = {}
        for src, dst in (("conversation_id", "conversation_id"), ("reply_with", "in_reply_to")):
            value = obj.get(src)
            if isinstance(value, str) and len(value) <= 200:
                fields[dst] = value
        try:
            return ACLMessage(
                performative=Performative.NOT_UNDERSTOOD,
                sender=me,
                receivers=[sender],
                content=reason,
                **fields,
            )
        except Exception:
            return None  # the claimed sender is not a valid identifier
