"""The asyncio agent: a bounded mailbox, handlers chosen by templates, conversations.

An agent lives on an `AgentPlatform` (``await platform.add(agent)``), which owns its task.
Inside, the agent owns its own ``asyncio.TaskGroup``: the receive loop
(``agent[name@platform].receive``), handlers declared ``concurrent`` and whatever it
``spawn``s. Stopping cancels them all; nothing outlives the agent.

How an incoming message is routed, in order:

1. to the open `Conversation` waiting for it: by ``in_reply_to`` (the ``reply_with`` of
   what the conversation sent), else by ``conversation_id``; only from the conversation's
   peers. This happens on delivery, so an initiator waiting inside a handler is not
   blocked by its own mailbox;
2. else into the mailbox, then to the first handler whose `MessageTemplate` matches;
3. else a late reply to a conversation that just ended is dropped (counted), a stray
   ``not-understood`` or ``failure`` is logged, and anything else gets a
   ``not-understood`` saying why.

A handler that raises does not stop the agent: the error is logged and, when the message
expects a reply, the sender gets a ``failure`` with the reason.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import time
import traceback
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Coroutine, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple, Self

from ._acl import ACLMessage, Performative, agent_id, compose, new_id, platform_of
from ._aio import _TIMED_OUT, Deadlines, KeepCancelled, Mailbox, _expire
from ._exceptions import AgentError
from ._quote import quoted
from ._records import Record

if TYPE_CHECKING:
    from ._platform import AgentPlatform

_setattr = object.__setattr__  # a fixed MessageTemplate's fields, set once in __init__

log = logging.getLogger(__name__)

Handler = Callable[[ACLMessage], Awaitable[None]]
"""Handles one message; replies, if any, are sent by the handler itself."""

_P = Performative

# Performatives whose sender waits for an answer: a handler that raises answers `failure`.
EXPECTS_REPLY = frozenset(
    {
        _P.REQUEST,
        _P.REQUEST_WHEN,
        _P.REQUEST_WHENEVER,
        _P.QUERY_IF,
        _P.QUERY_REF,
        _P.SUBSCRIBE,
        _P.CFP,
        _P.ACCEPT_PROPOSAL,
        _P.PROPAGATE,
        _P.PROXY,
        _P.CANCEL,
    }
)
# Never answered automatically: answering them could start an endless exchange.
NEVER_ANSWERED = frozenset({_P.NOT_UNDERSTOOD, _P.FAILURE})

_MAX_REASON = 1000
# an ontology or protocol name another platform sent, as a not-understood names it
_NAME_QUOTED = 64


class ConversationError(AgentError):
    """A step of an interaction protocol did not go as the initiator needed."""

    def __init__(self, text: str, message: ACLMessage | None = None) -> None:
        self.message = message
        super().__init__(text)


class ReplyTimeout(ConversationError, TimeoutError):
    """No reply came before the deadline (``reply_by`` or the caller's timeout)."""


class Refused(ConversationError):
    """The responder refused the request; ``message`` is the refuse."""


class Failed(ConversationError):
    """The responder could not perform what it agreed to; ``message`` is the failure."""


class NotUnderstood(ConversationError):
    """The responder did not understand the message; ``message`` says why."""


_current_agent: contextvars.ContextVar[Agent | None] = contextvars.ContextVar(
    "dyknow_current_agent", default=None
)


def expects_reply(message: ACLMessage) -> bool:
    """Whether the sender of ``message`` waits for an answer (its act asks, or reply_with)."""
    if message.performative in NEVER_ANSWERED:
        return False
    return message.performative in EXPECTS_REPLY or message.reply_with is not None


def failure_of(exc: BaseException) -> str:
    """An exception for a log: its type and where it was raised, not its text (an error may
    quote the decrypted message it failed on: a value, a key)."""
    kinds = [type(exc).__qualname__]
    seen = {id(exc)}
    cause = exc.__cause__ or exc.__context__
    while cause is not None and id(cause) not in seen and len(kinds) < 4:
        seen.add(id(cause))
        kinds.append(f"from {type(cause).__qualname__}")
        cause = cause.__cause__ or cause.__context__
    frames = "".join(traceback.format_tb(exc.__traceback__)).rstrip()
    return f"{' '.join(kinds)} (its text left out), raised at:\n{frames}"


def reason_of(exc: BaseException) -> str:
    """A short, one-line reason for an error, as a failure or not-understood carries it."""
    text = str(exc)
    reason = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return reason if len(reason) <= _MAX_REASON else reason[:_MAX_REASON] + "…"


class MessageTemplate:
    """Matches messages on any subset of performative(s), protocol, ontology, conversation id.

    ``where`` is an extra predicate for what the fields cannot say. A template with
    nothing set matches every message. A template is fixed once made (an agent keeps
    the route it chose for a header: `Agent._receive_loop`).
    """

    __slots__ = ("conversation_id", "ontology", "performatives", "protocol", "where")

    def __init__(
        self,
        performative: Performative | str | Iterable[Performative | str] | None = None,
        *,
        protocol: str | None = None,
        ontology: str | None = None,
        conversation_id: str | None = None,
        where: Callable[[ACLMessage], bool] | None = None,
    ) -> None:
        performatives: frozenset[Performative] | None
        if performative is None:
            performatives = None
        elif isinstance(performative, str):
            performatives = frozenset({Performative(performative)})
        else:
            performatives = frozenset(Performative(p) for p in performative)
        _setattr(self, "performatives", performatives)
        _setattr(self, "protocol", protocol)
        _setattr(self, "ontology", ontology)
        _setattr(self, "conversation_id", conversation_id)
        _setattr(self, "where", where)

    if TYPE_CHECKING:
        performatives: frozenset[Performative] | None
        protocol: str | None
        ontology: str | None
        conversation_id: str | None
        where: Callable[[ACLMessage], bool] | None

    def __setattr__(self, name: str, value: Any) -> None:
        # only the template's own fields are fixed: a subclass keeps its attributes its own
        if name in _TEMPLATE_FIELDS:
            raise AttributeError(
                f"a MessageTemplate is fixed once made (set {name!r} in a new one)"
            )
        _setattr(self, name, value)

    def __delattr__(self, name: str) -> None:
        if name in _TEMPLATE_FIELDS:
            raise AttributeError(f"a MessageTemplate is fixed once made (cannot delete {name!r})")
        object.__delattr__(self, name)

    def __setstate__(self, state: Any) -> None:
        # copied and pickled as before (a subclass's as itself): the default sets each
        # slot through __setattr__, which refuses
        for fields in state if isinstance(state, tuple) else (state,):
            for name, value in (fields or {}).items():
                _setattr(self, name, value)

    def matches(self, message: ACLMessage) -> bool:
        """Whether ``message`` has every field this template sets."""
        return (
            (self.performatives is None or message.performative in self.performatives)
            and (self.protocol is None or message.protocol == self.protocol)
            and (self.ontology is None or message.ontology == self.ontology)
            and (self.conversation_id is None or message.conversation_id == self.conversation_id)
            and (self.where is None or self.where(message))
        )

    def __repr__(self) -> str:
        parts = []
        if self.performatives is not None:
            parts.append("|".join(sorted(self.performatives)))
        for field in ("protocol", "ontology", "conversation_id"):
            if (value := getattr(self, field)) is not None:
                parts.append(f"{field}={value!r}")
        if self.where is not None:
            parts.append("where=…")
        return f"MessageTemplate({', '.join(parts)})"


_TEMPLATE_FIELDS = frozenset(MessageTemplate.__slots__)


class _Route(NamedTuple):
    template: MessageTemplate
    handler: Handler
    concurrent: bool


class RouteSpec:
    """A handler declared on a function by a decorator (`on`, `on_request` …).

    ``make`` turns the agent and the bound function into the handler (the protocol
    decorators wrap it); ``fallback`` routes are tried after all the others.
    """

    # a plain class, not a dataclass: generating a dataclass's methods costs ~0.4 ms of a
    # node's start; these are only built by the decorators and read by `Agent`
    __slots__ = ("concurrent", "fallback", "make", "template")

    def __init__(
        self,
        template: MessageTemplate,
        concurrent: bool = False,
        fallback: bool = False,
        make: Callable[[Agent, Callable[..., Any]], Handler] | None = None,
    ) -> None:
        self.template = template
        self.concurrent = concurrent
        self.fallback = fallback
        self.make = make


_SPECS = "__agent_routes__"


def mark(fn: Any, spec: RouteSpec) -> None:
    """Attach a route declaration to ``fn`` (what handler decorators do)."""
    specs = getattr(fn, _SPECS, None)
    if specs is None:
        specs = []
        setattr(fn, _SPECS, specs)
    specs.append(spec)


def declare(*specs: RouteSpec) -> Callable[[Any], Any]:
    """The decorator that attaches ``specs`` to a function (what handler decorators return)."""

    def decorate(fn: Any) -> Any:
        for spec in specs:
            mark(fn, spec)
        return fn

    return decorate


def on(template: MessageTemplate, *, concurrent: bool = False) -> Callable[[Any], Any]:
    """Declare an agent method ``async def h(self, message)`` as the handler for ``template``.

    ``concurrent=True`` runs each message in its own task (owned by the agent), for
    handlers that wait (on another agent, a timer) and must not hold up the mailbox.
    """
    return declare(RouteSpec(template, concurrent))


def _class_specs(cls: type) -> list[tuple[str, RouteSpec]]:
    """The route declarations of ``cls``: subclasses' before their bases', in definition order.

    A method overridden in a subclass keeps only the subclass's declarations (or none).
    """
    cached: list[tuple[str, RouteSpec]] | None = cls.__dict__.get("_route_specs_cache")
    if cached is not None:
        return cached
    seen: set[str] = set()
    specs: list[tuple[str, RouteSpec]] = []
    for klass in cls.__mro__:
        for attr, value in vars(klass).items():
            if attr in seen or attr.startswith("__"):
                continue
            seen.add(attr)
            fn = value.__func__ if isinstance(value, staticmethod | classmethod) else value
            specs.extend((attr, spec) for spec in getattr(fn, _SPECS, ()))
    cls._route_specs_cache = specs  # type: ignore[attr-defined]
    return specs


@dataclass(init=False, repr=False, eq=False)
class AgentStats(Record):
    """What an agent has seen: messages handled, answered not-understood, dropped …"""

    __slots__ = (
        "answered_at_once",
        "conversation_overflow",
        "dropped",
        "handled",
        "handler_errors",
        "late",
        "not_understood",
        "received",
        "unsolicited",
    )
    received: int
    handled: int
    handler_errors: int
    not_understood: int
    unsolicited: int
    late: int
    dropped: int
    conversation_overflow: int
    answered_at_once: int
    """Of ``handled``: answered by `Agent.answer_at_once` as they came (no mailbox, no task)."""

    def __init__(
        self,
        received: int = 0,
        handled: int = 0,
        handler_errors: int = 0,
        not_understood: int = 0,
        unsolicited: int = 0,
        late: int = 0,
        dropped: int = 0,
        conversation_overflow: int = 0,
        answered_at_once: int = 0,
    ) -> None:
        self.received = received
        self.handled = handled
        self.handler_errors = handler_errors
        self.not_understood = not_understood
        self.unsolicited = unsolicited
        self.late = late
        self.dropped = dropped
        self.conversation_overflow = conversation_overflow
        self.answered_at_once = answered_at_once


class _Later:
    """The type of `LATER`."""

    __slots__ = ()

    def __repr__(self) -> str:
        return "LATER"


LATER: Any = _Later()
"""What `Agent.answer_at_once` returns for a message it leaves to the handlers."""


class _Ended:
    """Put in a conversation's queue when it is closed: `receive` raises after the rest."""

    __slots__ = ("error",)

    def __init__(self, error: BaseException | None) -> None:
        self.error = error


_CLOSED_KEPT = 4096  # the ids of closed conversations an agent remembers (late replies)
_new = object.__new__  # an instance not yet initialized (see `Conversation.__init__`)
_CLOSED = _Ended(None)  # the end of every conversation closed without an error: one object


class Conversation:
    """The initiator's end of one conversation: the replies matched to it, in order.

    Open with `Agent.conversation` (a context manager: closing unregisters it, in
    ``finally``). Messages sent with `send` register their ``reply_with`` so answers are
    matched by ``in_reply_to``; answers carrying the ``conversation_id`` match too. Only
    messages from ``peers`` (when given) are taken. `receive` waits until the
    conversation's deadline and raises `ReplyTimeout` after it, never hangs past it.
    """

    __slots__ = (
        "_agent",
        "_gathers",
        "_items",
        "_keys",
        "closed",
        "deadline",
        "id",
        "last_sent",
        "maxlen",
        "peers",
    )

    def __init__(
        self,
        agent: Agent,
        conversation_id: str | None,
        *,
        peers: Iterable[str] | None = None,
        deadline: float | None = None,
        maxlen: int = 4096,
    ) -> None:
        self._agent = agent
        self.id = conversation_id
        self.peers = frozenset(peers) if peers is not None else None
        self.deadline = deadline  # loop time
        self.maxlen = maxlen
        # overflow drops the oldest reply (counted and logged in _put)
        # made and initialized in two calls: a class call with keywords takes the type's
        # slow path (its arguments packed into a tuple and a dict), ~1 µs a request more
        self._items: Mailbox[ACLMessage | _Ended] = _new(Mailbox)
        self._items.__init__(maxlen, drop_oldest=True)  # type: ignore[misc]
        self._keys: list[str] = []
        self.closed = False
        self.last_sent: ACLMessage | None = None
        # each waiting `gather`: who has not answered yet, and the future that ends its wait
        self._gathers: list[tuple[set[str], asyncio.Future[None]]] = []
        if conversation_id is not None:
            agent._by_conv[conversation_id] = self

    def expect(self, reply_with: str) -> None:
        """Take the answers to a message sent with ``reply_with`` (``in_reply_to`` match)."""
        self._keys.append(reply_with)
        self._agent._by_reply[reply_with] = self

    def accepts(self, message: ACLMessage) -> bool:
        """Whether ``message`` belongs here (from a peer, and not one of our own messages)."""
        if self.closed or (self.peers is not None and message.sender not in self.peers):
            return False
        rw = message.reply_with
        return rw is None or rw not in self._keys  # an agent asking itself sees its request

    def send(self, message: ACLMessage) -> Coroutine[Any, Any, None]:
        """Send ``message`` within this conversation, expecting answers to its reply_with: await it.

        A plain call returning `Agent.send`'s coroutine, a coroutine less per message sent.
        """
        reply_with = message.reply_with
        if reply_with is not None:  # `expect`, inline
            self._keys.append(reply_with)
            self._agent._by_reply[reply_with] = self
        self.last_sent = message
        return self._agent.send(message)

    def _put(self, message: ACLMessage) -> None:
        # `self._items.put(message)`, inline (the path of every reply): a conversation's
        # box drops its oldest when full (`__init__`)
        box = self._items
        items = box._items
        full = len(items) >= box.maxlen
        if full:
            box.dropped += 1
            items.popleft()
        items.append(message)
        w = box._waiter
        if w is not None and not w.done():
            w.set_result(None)
        if full:
            self._agent.stats.conversation_overflow += 1
            log.warning(
                "%s: conversation %s overflowed; oldest reply dropped", self._agent, self.id
            )
        if self._gathers and message.performative is not Performative.AGREE:
            sender = message.sender
            for awaiting, done in self._gathers:
                if sender in awaiting:
                    awaiting.discard(sender)
                    if not awaiting:
                        _settle(done)

    def unread(self, message: ACLMessage) -> None:
        """Put ``message`` back in front, to be received again."""
        self._items.put_front(message)

    def pending(self) -> int:
        """How many received messages wait to be read."""
        n = len(self._items)
        # once closed, the end marker is the last item, and nothing comes after it
        return n - 1 if n and self.closed else n

    def drain(self) -> list[ACLMessage]:
        """Every message queued now, in order, taken without waiting (as `receive` takes them).

        For a reader of many answers once `gather` returned: all that came, in one call.
        The end of a closed conversation stays queued (it is always last), for `receive`
        to raise.
        """
        taken = self._items.get_all_nowait()
        if taken and type(taken[-1]) is _Ended:
            self._items.put_front(taken.pop())
        return taken  # type: ignore[return-value]

    async def receive(
        self, *, deadline: float | None = None, timeout: float | None = None
    ) -> ACLMessage:
        """The next message; ReplyTimeout at ``deadline`` (loop time) or after ``timeout`` s.

        Without either, the conversation's deadline applies (none: wait as long as it takes).
        """
        if timeout is not None:
            deadline = asyncio.get_running_loop().time() + timeout
        elif deadline is None:
            deadline = self.deadline
        items = self._items
        queued = items._items
        # `closed` first: `not items` is a call of Mailbox.__len__
        if self.closed and not queued:
            raise ConversationError(f"conversation {self.id} is closed", self.last_sent)
        if not queued:
            # `items.get(deadline, loop=..., deadlines=...)`, inline: a coroutine less per
            # reply awaited (each wake passes through every coroutine awaiting)
            agent = self._agent
            loop = agent._loop or asyncio.get_running_loop()
            deadlines = agent._deadlines
            while not queued:
                items._waiter = w = loop.create_future()
                timer = None
                try:  # a deadline refused leaves no waiter behind
                    if deadline is None:
                        pass
                    elif deadlines is not None:
                        deadlines.add(deadline, w)
                    else:
                        timer = loop.call_at(deadline, _expire, w)
                    await w
                finally:
                    items._waiter = None
                    if timer is not None:
                        timer.cancel()
                if w.result() is _TIMED_OUT and not queued:
                    raise ReplyTimeout(
                        f"no reply from {self._peers_text()} in conversation {self.id}",
                        self.last_sent,
                    )
        item = queued.popleft()
        # not isinstance: for a message that is none, it reads the message's __class__
        # through pydantic's attribute hook (_Ended has no subclass)
        if type(item) is _Ended:
            items.put_front(item)  # stays ended for later calls
            raise item.error or ConversationError(
                f"conversation {self.id} is closed", self.last_sent
            )
        return item  # type: ignore[return-value]  # a message: the end marker is raised above

    async def gather(self, senders: Iterable[str], *, deadline: float | None = None) -> None:
        """Wait until each of ``senders`` has answered (an agree is no answer yet), or ``deadline``.

        ``deadline`` is loop time (None: the conversation's). The answers stay queued: `receive`
        then returns each without waiting, and raises as always once they are read (the
        deadline passed, the conversation closed). A reader of many peers' answers wakes
        once for all of them rather than once per answer. Returns at the deadline or
        when the conversation closes without raising.
        """
        awaiting = set(senders)
        if awaiting:
            agree = Performative.AGREE
            for item in self._items._items:  # what came already
                if isinstance(item, _Ended):
                    return
                if item.performative is not agree:
                    awaiting.discard(item.sender)
        if not awaiting or self.closed:
            return
        if deadline is None:
            deadline = self.deadline
        loop = self._agent._loop or asyncio.get_running_loop()
        done: asyncio.Future[None] = loop.create_future()
        # one entry per waiter: gathers of one conversation in several tasks each wake
        gathering = (awaiting, done)
        self._gathers.append(gathering)
        timer = None if deadline is None else loop.call_at(deadline, _settle, done)
        try:
            await done
        finally:
            self._gathers.remove(gathering)
            if timer is not None:
                timer.cancel()

    def _peers_text(self) -> str:
        return ", ".join(sorted(self.peers)) if self.peers else "anyone"

    def close(self, error: BaseException | None = None) -> None:
        """Unregister; a waiting `receive` raises ``error`` (or ConversationError)."""
        if self.closed:
            return
        self.closed = True
        agent = self._agent
        # the agent remembers the closed ids (the last `_CLOSED_KEPT`) for late replies
        closed = agent._closed_keys
        if self.id is not None and agent._by_conv.get(self.id) is self:
            del agent._by_conv[self.id]
            closed[self.id] = None
        for key in self._keys:
            if agent._by_reply.get(key) is self:
                del agent._by_reply[key]
                closed[key] = None
        while len(closed) > _CLOSED_KEPT:
            closed.popitem(last=False)
        # `self._items.put(..., force=True)`, inline: the end marker goes in even when full
        box = self._items
        box._items.append(_CLOSED if error is None else _Ended(error))
        w = box._waiter
        if w is not None and not w.done():
            w.set_result(None)
        for _, done in self._gathers:
            _settle(done)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _settle(waiter: asyncio.Future[None] | None) -> None:
    """End a `Conversation.gather` wait (all answered, its deadline, the conversation closed)."""
    if waiter is not None and not waiter.done():
        waiter.set_result(None)


_UNATTACHED, _STARTING, _RUNNING, _STOPPING, _STOPPED = (
    "unattached",
    "starting",
    "running",
    "stopping",
    "stopped",
)


class Agent:
    """An agent: identifier ``name@platform``, a bounded mailbox, handlers chosen by templates.

    Subclass it and declare handlers with `on` (or the protocol decorators in
    `agents.on_request` …), or add them with `add_handler`. Start it with
    ``await platform.add(agent)``; stop it with `stop` or by leaving
    ``async with await platform.add(agent):``. `setup` and `teardown` are hooks run as
    the agent starts (before it is ready) and stops (while it can still send).
    """

    mailbox_size = 16384

    answer_at_once: Callable[[ACLMessage], Any] | None = None
    """A read that never waits, answered as the message comes; None: every message queued.

    Define it as a method ``def answer_at_once(self, message)`` returning the content of
    the ``inform`` that answers ``message`` (as an `on_query` / `on_request` handler's
    result), or `LATER` to leave the message to the mailbox and handlers. The Interface
    Agent calls it on the event loop for a request (query, subscribe …) of another
    platform that came alone, once admitted (limits, directory, audit), when nothing
    waits in this agent's mailbox, its receive loop is in no handler and no concurrent
    handler's task is yet to start (so it overtakes nothing that came before it), it is
    not a reply to one of its conversations and the answer can be sealed and sent at
    once (else it is not asked: the message is queued and the handler answers it). It
    must not wait, block or change state: for reads only. An exception it raises is
    taken as `LATER`.
    """

    answer_on_thread: Callable[[ACLMessage], Any] | None = None
    """`answer_at_once` on the transport's thread, before the event loop wakes; None: not so.

    Asked by the Interface Agent on zenoh's receiving thread (`InterfaceAgent.lane`) for
    a message `answer_at_once` would be asked for, under the same conditions. It runs
    beside the event loop: it may read only what the loop replaces whole (a tuple, a
    snapshot) and must give the answer `answer_at_once` gives at some moment of that
    read, or `LATER` (the message then takes the loop's way, where `answer_at_once`
    decides it). The Federation and Gateway Agents define it.
    """

    def __init__(self, name: str, *, mailbox_size: int | None = None) -> None:
        agent_id(name, "platform")  # check the name's characters now, not on start
        self.name = name
        self.aid = name  # becomes name@platform when added to a platform
        self.stats = AgentStats()
        self._platform: AgentPlatform | None = None
        self._mailbox: Mailbox[ACLMessage] = Mailbox(mailbox_size or self.mailbox_size)
        self._routes: list[_Route] = []
        self._fallbacks: list[_Route] = []
        self._by_reply: dict[str, Conversation] = {}
        self._by_conv: dict[str, Conversation] = {}
        self._closed_keys: OrderedDict[str, None] = OrderedDict()
        # concurrent handlers' tasks spawned, not yet started (truthy: `answer_at_once`
        # waits); a set, not a count, so that a task cancelled before its first step,
        # whose `_handle` never runs, leaves it when it ends
        self._handlers_starting: set[asyncio.Task[Any]] = set()
        self._state = _UNATTACHED
        self._task: asyncio.Task[None] | None = None
        self._tg: asyncio.TaskGroup | None = None
        self._children: set[asyncio.Task[Any]] = set()
        self._stop_requested: asyncio.Future[None] | None = None
        # the loop the agent runs on, from its start until it stops: looking it up costs
        # a system call (getpid) in Python 3.11, and conversations need it every time
        self._loop: asyncio.AbstractEventLoop | None = None
        # the deadlines of its conversations' waits, on that loop (one timer for all)
        self._deadlines: Deadlines | None = None
        for attr, spec in _class_specs(type(self)):
            bound = getattr(self, attr)
            handler = spec.make(self, bound) if spec.make is not None else bound
            route = _Route(spec.template, handler, spec.concurrent)
            (self._fallbacks if spec.fallback else self._routes).append(route)
        # which route a header chooses is remembered (`_receive_loop`) while this version
        # of the routes holds and no template has a predicate (a header alone decides)
        self._routes_version = 0
        self._routes_memo = False
        self._routes_changed()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.aid} {self._state}>"

    def __str__(self) -> str:
        return f"agent[{self.aid}]"

    # -- handlers ---------------------------------------------------------------------

    def add_handler(
        self, template: MessageTemplate, handler: Handler, *, concurrent: bool = False
    ) -> Callable[[], None]:
        """Handle messages matching ``template`` (after the class's handlers); returns a remover."""
        route = _Route(template, handler, concurrent)
        self._routes.append(route)
        self._routes_changed()

        def remove() -> None:
            if route in self._routes:
                self._routes.remove(route)
                self._routes_changed()

        return remove

    def add_responder(self, fn: Callable[..., Any]) -> Callable[[], None]:
        """Add the handlers a decorator (`on`, `on_request` …) declared on a plain function."""
        removers = []
        for spec in getattr(fn, _SPECS, ()):
            handler = spec.make(self, fn) if spec.make is not None else fn
            route = _Route(spec.template, handler, spec.concurrent)
            (self._fallbacks if spec.fallback else self._routes).append(route)
            removers.append(route)
        if not removers:
            raise AgentError(f"{fn!r} declares no handler (decorate it with on/on_request …)")
        self._routes_changed()

        def remove() -> None:
            for route in removers:
                for routes in (self._routes, self._fallbacks):
                    if route in routes:
                        routes.remove(route)
            self._routes_changed()

        return remove

    def _routes_changed(self) -> None:
        """The routes changed: the receive loop chooses afresh (`_receive_loop`'s memo)."""
        self._routes_version += 1
        # a subclass's own `matches` may read any field (the sender, the content): only a
        # plain template without a predicate is decided by the header alone
        self._routes_memo = all(
            type(route.template) is MessageTemplate and route.template.where is None
            for route in (*self._routes, *self._fallbacks)
        )

    # -- lifecycle --------------------------------------------------------------------

    @property
    def platform(self) -> AgentPlatform:
        """The platform hosting this agent (AgentError before it is added to one)."""
        if self._platform is None:
            raise AgentError(f"agent {self.name!r} is not on a platform")
        return self._platform

    @property
    def running(self) -> bool:
        """Whether the agent is started and not stopping."""
        return self._state == _RUNNING

    async def setup(self) -> None:
        """Hook: run as the agent starts, before it is ready (it can already send)."""

    async def teardown(self) -> None:
        """Hook: run as the agent stops, while it can still send."""

    async def _start(self, platform: AgentPlatform, tg: asyncio.TaskGroup) -> None:
        """Start on ``platform``, the agent's task owned by ``tg``; returns once it is ready."""
        if self._state != _UNATTACHED:
            raise AgentError(f"{self} is {self._state}; an agent starts once")
        self._platform = platform
        self.aid = agent_id(self.name, platform.name)
        self._state = _STARTING
        loop = self._loop = asyncio.get_running_loop()
        self._deadlines = Deadlines(loop)
        ready: asyncio.Future[None] = loop.create_future()
        self._stop_requested = loop.create_future()
        self._task = tg.create_task(self._run(ready), name=f"agent[{self.aid}]")
        try:
            await ready
        except BaseException:
            # given up just as it got ready (the cancel came after its ready was told):
            # it stops, as one given up while its setup ran does; else it would run on
            # unlisted, and hold its platform's close forever
            told = ready.done() and not ready.cancelled() and ready.exception() is None
            if told and not self._stop_requested.done():
                self._stop_requested.set_result(None)
            raise

    async def _run(self, ready: asyncio.Future[None]) -> None:
        _current_agent.set(self)
        assert self._stop_requested is not None
        again: KeepCancelled | None = None
        try:
            async with asyncio.TaskGroup() as tg:
                self._tg = tg
                await self.setup()
                self._spawn(self._receive_loop(), "receive")
                self._state = _RUNNING
                if ready.cancelled():
                    # its start was given up (the add cancelled) while setup ran: it
                    # stops at once, its teardown undoing what the setup made
                    if not self._stop_requested.done():
                        self._stop_requested.set_result(None)
                else:
                    ready.set_result(None)
                await self._stop_requested
                try:
                    await self.teardown()
                except Exception:
                    log.exception("%s: teardown failed", self)
                self._state = _STOPPING
                for task in list(self._children):
                    task.cancel()
                # one that lost its cancellation would hold the stop forever
                again = KeepCancelled(lambda: self._children)
            await self._refuse_queued()
        except Exception as exc:
            # The platform's task group must survive one bad agent: report, do not raise.
            err = _unwrap(exc)
            if not ready.done():
                ready.set_exception(err)
            else:
                log.error("%s crashed", self, exc_info=err)
        except BaseException:
            if not ready.done():
                ready.set_exception(AgentError(f"{self} was cancelled while starting"))
            raise
        finally:
            if again is not None:
                again.stop()
            self._state = _STOPPED
            self._tg = None
            self._loop = None
            deadlines, self._deadlines = self._deadlines, None
            err = ConversationError(f"{self} stopped")
            for conv in {*self._by_conv.values(), *self._by_reply.values()}:
                conv.close(err)
            if deadlines is not None:
                # its timer would hold what ended until the last deadline (an hour's
                # timeout: an hour); a wait still in it (a conversation of no id and no
                # key is not closed here) still ends by it
                deadlines.drop_ended()
            if self._platform is not None:
                self._platform._forget(self)

    async def _refuse_queued(self) -> None:
        """Answer what is still in the mailbox and waits for an answer: we will not."""
        mailbox = self._mailbox
        while len(mailbox):
            message = mailbox.get_nowait()
            if expects_reply(message):
                await self._answer(message, Performative.FAILURE, f"{self.aid} stopped")

    async def stop(self) -> None:
        """Stop: run `teardown`, cancel every task of the agent, wait until it is done.

        Called from the agent's own tasks, it only asks (it cannot wait for itself).
        """
        task = self._task
        if task is None or task.done():
            return
        if self._stop_requested is not None and not self._stop_requested.done():
            self._stop_requested.set_result(None)
        if _current_agent.get() is self:
            return
        await asyncio.wait([task])  # not `await task`: our cancellation must not cancel it

    async def __aenter__(self) -> Self:
        if self._state not in (_RUNNING, _STARTING):
            raise AgentError(f"{self} is {self._state}: add it to a platform first")
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    def spawn(self, coro: Coroutine[Any, Any, Any], name: str) -> asyncio.Task[Any]:
        """Run ``coro`` as a task owned by the agent (``agent[aid].name``); errors are logged."""
        try:
            task = self._spawn(self._guard(coro, name), name)
        except AgentError:
            coro.close()  # refused: never to run, not left to warn that it was never awaited
            raise
        # cancelled before its first step (a start given up), the guard never awaits
        # ``coro``: close it then
        task.add_done_callback(lambda _: coro.close())
        return task

    def _spawn(self, coro: Coroutine[Any, Any, Any], name: str) -> asyncio.Task[Any]:
        if self._tg is None or self._state in (_STOPPING, _STOPPED):
            coro.close()
            raise AgentError(f"{self} is {self._state}: it cannot start tasks")
        try:
            task = self._tg.create_task(coro, name=f"agent[{self.aid}].{name}")
        except RuntimeError as exc:
            # its task group is shutting down: the agent's task was cancelled (a close cut
            # short) while it still counts as running
            coro.close()
            raise AgentError(f"{self} is being cancelled: it cannot start tasks") from exc
        self._children.add(task)
        task.add_done_callback(self._children.discard)
        return task

    async def _guard(self, coro: Coroutine[Any, Any, Any], name: str) -> None:
        try:
            await coro
        except Exception:
            log.exception("%s: task %s failed", self, name)

    # -- sending ----------------------------------------------------------------------

    def message(
        self,
        performative: Performative | str,
        receivers: str | Iterable[str],
        content: Any = None,
        **fields: Any,
    ) -> ACLMessage:
        """A new message from this agent (other ACL fields as keywords)."""
        return compose(performative, self.aid, receivers, content, fields)

    def send(self, message: ACLMessage) -> Coroutine[Any, Any, None]:
        """Send ``message`` (its sender must be this agent) to its receivers: await it.

        A plain call returning the platform's coroutine, a coroutine less per message sent.
        """
        if message.sender != self.aid:
            raise AgentError(f"{self} cannot send as {message.sender}")
        if self._platform is None:
            raise AgentError(f"{self} is not on a platform")
        return self._platform.send(message)

    async def reply(
        self,
        message: ACLMessage,
        performative: Performative,
        content: Any = None,
        *,
        reply_with: str | None = None,
    ) -> ACLMessage:
        """Answer ``message`` (same conversation, in_reply_to its reply_with); return the answer."""
        answer = message.reply(performative, content, sender=self.aid)
        if reply_with is not None:
            answer = answer.model_copy(update={"reply_with": reply_with})
        if performative == Performative.REFUSE and self._platform is not None:
            self._platform.agent_refused(message, content)  # counted, audited summed up
        await self.send(answer)
        return answer

    def conversation(
        self,
        conversation_id: str | None = None,
        *,
        peers: Iterable[str] | None = None,
        timeout: float | None = None,
        maxlen: int = 4096,
    ) -> Conversation:
        """Open a conversation that collects the replies for us (use it in ``with``).

        ``timeout`` (s) sets the deadline of every `Conversation.receive` that gives none.
        """
        if conversation_id is not None and conversation_id in self._by_conv:
            raise AgentError(f"{self} already has conversation {conversation_id} open")
        deadline = None
        if timeout is not None:
            deadline = (self._loop or asyncio.get_running_loop()).time() + timeout
        conv = _new(Conversation)  # as its box is made (`Conversation.__init__`)
        conv.__init__(self, conversation_id, peers=peers, deadline=deadline, maxlen=maxlen)  # type: ignore[misc]
        return conv

    async def ask(self, message: ACLMessage, *, timeout: float) -> ACLMessage:
        """Send ``message`` and return the first answer; ReplyTimeout after ``timeout`` s.

        Sets conversation_id, reply_with and reply_by when the message has none.
        """
        update: dict[str, Any] = {}
        if message.conversation_id is None:
            update["conversation_id"] = new_id("c")
        if message.reply_with is None:
            update["reply_with"] = new_id("r")
        if message.reply_by is None:
            update["reply_by"] = time.time() + timeout
        if update:
            message = message.model_copy(update=update)
        with self.conversation(
            message.conversation_id, peers=message.receivers, timeout=timeout
        ) as conv:
            await conv.send(message)
            return await conv.receive()

    # -- receiving --------------------------------------------------------------------

    def _deliver(self, message: ACLMessage) -> bool:
        """Route an incoming message (sync); False when the mailbox is full."""
        # its fields read in __dict__ (a dict lookup each, not pydantic's attribute hook):
        # these have defaults, so every message holds them (model_construct's too)
        fields = message.__dict__
        conv = None
        if (key := fields["in_reply_to"]) is not None:
            conv = self._by_reply.get(key)
        if conv is None and (key := fields["conversation_id"]) is not None:
            conv = self._by_conv.get(key)
        if conv is not None:
            # `conv.accepts(message)`, inline: the path of every reply
            peers = conv.peers
            rw = fields["reply_with"]
            if (
                not conv.closed
                and (peers is None or fields["sender"] in peers)
                and (rw is None or rw not in conv._keys)
            ):
                self.stats.received += 1
                conv._put(message)
                return True
        if self._state in (_STOPPING, _STOPPED) or not self._mailbox.put(message):
            self.stats.dropped += 1
            return False
        self.stats.received += 1
        return True

    def _deliver_batch(self, messages: list[ACLMessage]) -> int:
        """`_deliver` each of ``messages``, in order, waking the receive loop once; how many taken.

        Replies still go to the conversation waiting for them; the rest go to the mailbox
        together (nothing runs in between, so each queue keeps the order a `_deliver` per
        message would give it).
        """
        stats = self.stats
        routed = 0
        if self._by_reply or self._by_conv:  # else none can be a conversation's
            by_reply, by_conv = self._by_reply, self._by_conv
            rest = []
            for message in messages:
                conv = None
                if message.in_reply_to is not None:
                    conv = by_reply.get(message.in_reply_to)
                if conv is None and message.conversation_id is not None:
                    conv = by_conv.get(message.conversation_id)
                if conv is not None and conv.accepts(message):
                    stats.received += 1
                    conv._put(message)
                    routed += 1
                else:
                    rest.append(message)
            messages = rest
        if self._state in (_STOPPING, _STOPPED):
            stats.dropped += len(messages)
            return routed
        taken = self._mailbox.put_many(messages)
        stats.received += taken
        stats.dropped += len(messages) - taken
        return routed + taken

    async def _receive_loop(self) -> None:
        mailbox = self._mailbox
        items, get = mailbox._items, mailbox.get
        loop = asyncio.get_running_loop()
        stats = self.stats
        # The route chosen last and the header it was chosen for: the same header objects
        # again (a batch's messages share the first one's, `InterfaceAgent._take_batch`)
        # choose the same route while the routes are unchanged and every template is a
        # plain one without a predicate (`_routes_changed`): the header alone decides
        # (`MessageTemplate.matches`), and templates are fixed. An identity test: an equal
        # header in other objects chooses afresh.
        version = -1
        route: _Route | None = None
        performative = protocol = ontology = conversation_id = None
        while True:
            # what is queued is taken without a coroutine call: a burst costs less
            message = items.popleft() if items else await get(loop=loop)
            fields = message.__dict__
            if not (
                version == self._routes_version
                and fields["performative"] is performative
                and fields["ontology"] is ontology
                and fields["protocol"] is protocol
                and fields["conversation_id"] is conversation_id
            ):
                version = -1
                try:
                    route = self._route_for(message)
                except Exception as exc:  # a template's `where` raised: the agent lives on
                    await self._failed(message, exc, "choosing a handler")
                    continue
                if self._routes_memo:
                    version = self._routes_version
                    performative, ontology = fields["performative"], fields["ontology"]
                    protocol, conversation_id = fields["protocol"], fields["conversation_id"]
            if route is None:
                await self._unhandled(message)
            elif route.concurrent:
                task = self._spawn(self._handle(route.handler, message), "handle")
                starting = self._handlers_starting
                starting.add(task)  # it starts in a later turn
                task.add_done_callback(starting.discard)
            else:
                # `_handle`, inline: the common case of every message
                try:
                    await route.handler(message)
                    stats.handled += 1
                except Exception as exc:
                    await self._failed(message, exc, "handler")
                except asyncio.CancelledError:
                    if self._state == _STOPPING and expects_reply(message):
                        await self._answer(message, Performative.FAILURE, f"{self.aid} stopped")
                    raise

    def _route_for(self, message: ACLMessage) -> _Route | None:
        for route in self._routes:
            if route.template.matches(message):
                return route
        for route in self._fallbacks:
            if route.template.matches(message):
                return route
        return None

    async def _handle(self, handler: Handler, message: ACLMessage) -> None:
        self._handlers_starting.discard(asyncio.current_task())
        try:
            await handler(message)
            self.stats.handled += 1
        except Exception as exc:
            await self._failed(message, exc, "handler")
        except asyncio.CancelledError:
            if self._state == _STOPPING and expects_reply(message):
                # Stopped mid-way: say so now rather than let the initiator time out.
                await self._answer(message, Performative.FAILURE, f"{self.aid} stopped")
            raise

    async def _failed(self, message: ACLMessage, exc: Exception, where: str) -> None:
        self.stats.handler_errors += 1
        if platform_of(message.sender) != platform_of(self.aid):
            # another platform's message came encrypted: the error's text may quote it
            # (pydantic's quotes the input it failed on); its sender gets it in the failure
            log.error(
                "%s: %s failed on %s from %s: %s",
                self,
                where,
                message.performative,
                message.sender,
                failure_of(exc),
            )
        else:
            log.error(
                "%s: %s failed on %s from %s",
                self,
                where,
                message.performative,
                message.sender,
                exc_info=exc,
            )
        if expects_reply(message):
            await self._answer(message, Performative.FAILURE, reason_of(exc))

    async def _unhandled(self, message: ACLMessage) -> None:
        closed = self._closed_keys
        if (message.in_reply_to is not None and message.in_reply_to in closed) or (
            message.conversation_id is not None and message.conversation_id in closed
        ):
            self.stats.late += 1
            log.debug("%s: late %s from %s dropped", self, message.performative, message.sender)
            return
        platform = self._platform
        if message.performative in NEVER_ANSWERED:
            # another platform may send these at will: a line (of its content) each would
            # let it fill the log; counted, audited summed up, logged now and then
            self.stats.unsolicited += 1
            n = self.stats.unsolicited
            what = f"unsolicited {message.performative} for {self.aid}"
            if n == 1 or n % 1000 == 0:
                # its content never: it came encrypted (the audit, sealed, keeps it)
                log.warning("%s: %s, from %s (%d since start)", self, what, message.sender, n)
            what = f"{what}: {message.content!r:.200}"
            if platform is not None:
                platform.agent_dropped(message, "unsolicited", what)
            return
        self.stats.not_understood += 1
        what = f"{message.performative}"
        # the sender's words, in the answer and the audit: on one line, bounded
        if message.protocol:
            what += f" (protocol {quoted(message.protocol, _NAME_QUOTED)})"
        if message.ontology:
            what += f" (ontology {quoted(message.ontology, _NAME_QUOTED)})"
        if platform is not None:
            platform.agent_dropped(message, "not-understood", f"{self.aid}: {what}"[:300])
        await self._answer(
            message, Performative.NOT_UNDERSTOOD, f"{self.aid} has no handler for {what}"
        )

    async def _answer(self, message: ACLMessage, performative: Performative, reason: str) -> None:
        """Send an automatic answer; a failure to send is logged, never raised."""
        try:
            await self.send(message.reply(performative, reason, sender=self.aid))
        except Exception:
            log.exception("%s: could not send %s to %s", self, performative, message.sender)


def _unwrap(exc: BaseException) -> BaseException:
    """The single error inside (nested) exception groups, else the group itself."""
    while isinstance(exc, BaseExceptionGroup) and len(exc.exceptions) == 1:
        exc = exc.exceptions[0]
    return exc
