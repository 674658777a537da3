"""FIPA interaction protocols, both sides: Request, Query, Subscribe, Contract-Net.

Initiators are async functions taking the initiating agent: they return the result
(the content of the final ``inform``) or raise `Refused`, `Failed`, `NotUnderstood` or
`ReplyTimeout` with the offending message attached (``exc.message``).

Responders are a few lines: decorate an agent method (or a function added with
`Agent.add_responder`) with `on_request`, `on_query`, `on_cfp`, `on_accept_proposal`;
return the content of the answer, or raise `Refuse` / `Failure`. Any other exception
becomes a ``failure`` too. FIPA-Subscribe's responder side is a `Publisher`.

Contents of refuse, failure and not-understood are a reason (usually a string).
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import time
from collections.abc import Awaitable, Callable, Coroutine, Iterable
from dataclasses import dataclass
from typing import Any, Self

from pydantic import JsonValue

from ._acl import ACLMessage, Performative, compose, new_id
from ._agent import (
    Agent,
    ConversationError,
    Failed,
    Handler,
    MessageTemplate,
    NotUnderstood,
    Refused,
    ReplyTimeout,
    RouteSpec,
    declare,
)
from ._records import Frozen, Record

log = logging.getLogger(__name__)

P = Performative
FIPA_REQUEST = "fipa-request"
FIPA_QUERY = "fipa-query"
FIPA_SUBSCRIBE = "fipa-subscribe"
FIPA_CONTRACT_NET = "fipa-contract-net"
DEFAULT_TIMEOUT = 10.0
"""Seconds an initiator waits for an answer when it is not told otherwise."""
_AGENT_MESSAGE = Agent.message


class Refuse(Exception):
    """Raised by a responder to answer ``refuse`` (``content``: the reason)."""

    def __init__(self, content: JsonValue = None) -> None:
        self.content = content
        super().__init__(content)


class Failure(Exception):
    """Raised by a responder to answer ``failure`` (``content``: the reason)."""

    def __init__(self, content: JsonValue = None) -> None:
        self.content = content
        super().__init__(content)


def _outcome(reply: ACLMessage, fields: dict[str, Any] | None = None) -> JsonValue:
    """The content of an ``inform``; raise the matching error for anything else.

    ``fields``: ``reply.__dict__`` when the caller read it already.
    """
    if fields is None:
        fields = reply.__dict__  # a received message holds every field: no attribute hook
    p = fields["performative"]
    if p is P.INFORM or p is P.INFORM_REF or p is P.INFORM_IF:
        return fields["content"]
    who = reply.sender
    if p is P.REFUSE:
        raise Refused(f"{who} refused: {reply.content}", reply)
    if p is P.FAILURE:
        raise Failed(f"{who} failed: {reply.content}", reply)
    if p is P.NOT_UNDERSTOOD:
        raise NotUnderstood(f"{who} did not understand: {reply.content}", reply)
    raise ConversationError(f"{who} answered {p}, which this protocol does not expect", reply)


def _opening(
    agent: Agent,
    performative: Performative,
    protocol: str,
    receivers: str | list[str],
    content: Any,
    *,
    ontology: str | None,
    language: str | None,
    timeout: float,
    conversation_id: str | None = None,
) -> ACLMessage:
    """An initiator's first message: a new conversation unless given, due in ``timeout`` s."""
    if conversation_id is None:
        conversation_id = new_id("c")
    fields = {
        "protocol": protocol,
        "ontology": ontology,
        "language": language,
        "conversation_id": conversation_id,
        "reply_with": new_id("r"),
        "reply_by": time.time() + timeout,
    }
    # an agent's own `message` (its class's, or one set on it) makes it, as it always did
    if type(agent).message is _AGENT_MESSAGE and "message" not in agent.__dict__:
        # `agent.message`, inline: passed as keywords, each of these fields (none a
        # parameter of it) is compared with each of its parameters first (~2.5 k Ir)
        return compose(performative, agent.aid, receivers, content, fields)
    return agent.message(performative, receivers, content, **fields)


async def _ask(
    agent: Agent,
    performative: Performative,
    protocol: str,
    receiver: str,
    content: Any,
    *,
    ontology: str | None,
    language: str | None,
    timeout: float,
    on_agree: Callable[[ACLMessage], None] | None = None,
    conversation_id: str | None = None,
) -> JsonValue:
    message = _opening(
        agent,
        performative,
        protocol,
        receiver,
        content,
        ontology=ontology,
        language=language,
        timeout=timeout,
        conversation_id=conversation_id,
    )
    # the id the message holds (an agent's own `message` may choose it), read without
    # pydantic's attribute hook: a message holds every field
    conv = agent.conversation(
        message.__dict__["conversation_id"], peers=(receiver,), timeout=timeout
    )
    try:  # `with conv`, without its two calls: closed however this ends
        await conv.send(message)
        reply = await conv.receive()
        fields = reply.__dict__  # one pass through pydantic's attribute hook, not two
        if fields["performative"] is P.AGREE:  # optional: the result follows
            if on_agree is not None:
                on_agree(reply)
            reply = await conv.receive()
            fields = reply.__dict__
        return _outcome(reply, fields)
    finally:
        conv.close()


def request(
    agent: Agent,
    receiver: str,
    content: Any = None,
    *,
    ontology: str | None = None,
    language: str | None = "json",
    timeout: float = DEFAULT_TIMEOUT,
    on_agree: Callable[[ACLMessage], None] | None = None,
    conversation_id: str | None = None,
) -> Coroutine[Any, Any, JsonValue]:
    """FIPA-Request: ask ``receiver`` to act; the content of its ``inform``: await it.

    An ``agree`` may come first (``on_agree`` sees it). ``timeout`` bounds the whole
    exchange and is sent as ``reply_by``. ``conversation_id`` (a new one by default)
    lets the caller send a FIPA ``cancel`` in the same conversation if it gives up.
    A plain call returning the exchange's coroutine (nothing runs before it is
    awaited), a coroutine less per request.
    """
    return _ask(
        agent,
        P.REQUEST,
        FIPA_REQUEST,
        receiver,
        content,
        ontology=ontology,
        language=language,
        timeout=timeout,
        on_agree=on_agree,
        conversation_id=conversation_id,
    )


async def query_ref(
    agent: Agent,
    receiver: str,
    content: Any = None,
    *,
    ontology: str | None = None,
    language: str | None = "json",
    timeout: float = DEFAULT_TIMEOUT,
) -> JsonValue:
    """FIPA-Query (query-ref): the object(s) ``content`` describes, as ``receiver`` informs."""
    return await _ask(
        agent,
        P.QUERY_REF,
        FIPA_QUERY,
        receiver,
        content,
        ontology=ontology,
        language=language,
        timeout=timeout,
    )


async def query_if(
    agent: Agent,
    receiver: str,
    content: Any = None,
    *,
    ontology: str | None = None,
    language: str | None = "json",
    timeout: float = DEFAULT_TIMEOUT,
) -> bool:
    """FIPA-Query (query-if): whether ``receiver`` believes the proposition ``content``."""
    answer = await _ask(
        agent,
        P.QUERY_IF,
        FIPA_QUERY,
        receiver,
        content,
        ontology=ontology,
        language=language,
        timeout=timeout,
    )
    if not isinstance(answer, bool):
        raise ConversationError(f"{receiver} answered query-if with {answer!r}, not true/false")
    return answer


# -- responders: request and query ---------------------------------------------------

Responder = Callable[[ACLMessage], Awaitable[Any]]
"""What a responder decorator wraps: gets the message, returns the answer's content."""


def _respond(
    agent: Agent,
    fn: Responder,
    *,
    agree: bool = False,
    can_refuse: bool = True,
    propose: bool = False,
) -> Handler:
    """The handler turning ``fn``'s result (inform or propose), Refuse or Failure into answers."""
    refuse = P.REFUSE if can_refuse and not agree else P.FAILURE

    async def handle(message: ACLMessage) -> None:
        try:
            if agree:
                await agent.reply(message, P.AGREE)
            result = await fn(message)
        except Refuse as exc:
            # After an agree (or an accepted proposal) the protocol only allows failure.
            await agent.reply(message, refuse, exc.content)
            return
        except Failure as exc:
            await agent.reply(message, P.FAILURE, exc.content)
            return
        if propose:  # an accept-proposal answers it, in reply to its own reply_with
            await agent.reply(message, P.PROPOSE, result, reply_with=new_id("r"))
        else:
            await agent.reply(message, P.INFORM, result)

    return handle


def on_request(
    ontology: str | None = None,
    *,
    protocol: str | None = None,
    agree: bool = False,
    concurrent: bool = False,
) -> Callable[[Any], Any]:
    """Declare a FIPA-Request responder: ``async def f(self, message) -> inform content``.

    Raise `Refuse` / `Failure` to refuse or fail. ``agree=True`` sends ``agree`` before
    running it (for long actions; the initiator's timeout still bounds the whole).
    """
    template = MessageTemplate(P.REQUEST, ontology=ontology, protocol=protocol)
    return declare(
        RouteSpec(template, concurrent, make=lambda agent, f: _respond(agent, f, agree=agree))
    )


def on_query(
    ontology: str | None = None, *, protocol: str | None = None, concurrent: bool = False
) -> Callable[[Any], Any]:
    """Declare a FIPA-Query responder for query-ref and query-if: returns the inform content.

    For query-if return True or False.
    """
    template = MessageTemplate((P.QUERY_REF, P.QUERY_IF), ontology=ontology, protocol=protocol)
    return declare(RouteSpec(template, concurrent, make=_respond))


# -- FIPA-Subscribe ------------------------------------------------------------------


class SubscriptionStream:
    """The initiator's side of a FIPA-Subscribe: an async iterator over the informs' contents.

    It ends cleanly (StopAsyncIteration) after `cancel` or when the responder ends the
    subscription with ``cancel``; a ``failure`` from the responder raises `Failed`. Use
    ``async with await subscribe(...) as stream: async for content in stream: …``;
    leaving the block cancels.
    """

    def __init__(
        self, agent: Agent, conversation: Any, subscribe_message: ACLMessage, agree: ACLMessage
    ) -> None:
        self.agent = agent
        self.responder = agree.sender
        self.message = subscribe_message
        self.agree = agree
        self.last: ACLMessage | None = None
        self._conv = conversation
        self._ended = False

    @property
    def ended(self) -> bool:
        """Whether no more informs will come."""
        return self._ended

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> JsonValue:
        try:
            return await self.get()
        except SubscriptionEnded:
            raise StopAsyncIteration from None

    async def get(self, timeout: float | None = None) -> JsonValue:
        """The next inform's content; ReplyTimeout after ``timeout`` s; SubscriptionEnded at end."""
        while True:
            if self._ended and not self._conv.pending():
                raise SubscriptionEnded(f"subscription {self._conv.id} ended")
            try:
                m = await self._conv.receive(timeout=timeout)
            except ReplyTimeout:
                raise
            except ConversationError:
                self._ended = True
                raise SubscriptionEnded(f"subscription {self._conv.id} ended") from None
            p = m.performative
            if p is P.INFORM:
                self.last = m
                return m.content
            if p is P.CANCEL:  # the responder ended it
                self._finish()
                raise SubscriptionEnded(f"subscription {self._conv.id} ended")
            if p is P.FAILURE:
                self._finish()
                raise Failed(f"{m.sender} ended the subscription: {m.content}", m)
            log.warning("%s: unexpected %s in subscription %s", self.agent, p, self._conv.id)

    def _finish(self) -> None:
        self._ended = True
        self._conv.close()

    async def cancel(self, *, timeout: float = 2.0) -> None:
        """Tell the responder to stop and wait (up to ``timeout`` s) for it to confirm."""
        if self._ended:
            return
        self._ended = True
        cancel = self.agent.message(
            P.CANCEL,
            self.responder,
            self.message.content,
            protocol=FIPA_SUBSCRIBE,
            ontology=self.message.ontology,
            conversation_id=self.message.conversation_id,
            in_reply_to=self.message.reply_with,
            reply_with=new_id("r"),
        )
        try:
            # Its own conversation (no id: matched by in_reply_to) so a reader of the
            # stream in another task does not take the confirmation.
            with self.agent.conversation(peers=(self.responder,), timeout=timeout) as confirm:
                await confirm.send(cancel)
                await confirm.receive()
        except ReplyTimeout:
            log.info("%s: %s did not confirm the cancel", self.agent, self.responder)
        except Exception:
            log.exception("%s: cancelling subscription %s", self.agent, self._conv.id)
        finally:
            self._conv.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.cancel()


class SubscriptionEnded(ConversationError):
    """The subscription is over: cancelled, or ended by the responder."""


async def subscribe(
    agent: Agent,
    receiver: str,
    content: Any = None,
    *,
    ontology: str | None = None,
    language: str | None = "json",
    timeout: float = DEFAULT_TIMEOUT,
    maxlen: int = 4096,
) -> SubscriptionStream:
    """FIPA-Subscribe: once ``receiver`` agrees, a stream of its informs until cancelled.

    ``timeout`` bounds the wait for the ``agree``; informs then come without deadline.
    Up to ``maxlen`` unread informs are kept (the oldest dropped beyond, and counted).
    """
    message = _opening(
        agent,
        P.SUBSCRIBE,
        FIPA_SUBSCRIBE,
        receiver,
        content,
        ontology=ontology,
        language=language,
        timeout=timeout,
    )
    conv = agent.conversation(message.conversation_id, peers=(receiver,), maxlen=maxlen)
    try:
        await conv.send(message)
        reply = await conv.receive(timeout=timeout)
        if reply.performative is P.INFORM:
            agree = reply  # FIPA lets the first inform stand for the agree
            conv.unread(reply)
        elif reply.performative is P.AGREE:
            agree = reply
        else:
            _outcome(reply)
            raise ConversationError(
                f"{receiver} answered subscribe with {reply.performative}", reply
            )
    except BaseException:
        conv.close()
        raise
    return SubscriptionStream(agent, conv, message, agree)


@dataclass(init=False, repr=False, eq=False)
class Subscriber(Record):
    """One subscription a `Publisher` serves: its subscribe message and what ``accept`` returned."""

    __slots__ = ("data", "message")
    message: ACLMessage
    data: Any

    def __init__(self, message: ACLMessage, data: Any = None) -> None:
        self.message = message
        self.data = data

    @property
    def agent(self) -> str:
        """The subscriber's agent identifier."""
        return self.message.sender


class Publisher:
    """The responder side of FIPA-Subscribe for one ontology on one agent.

    It answers ``subscribe`` (``agree``, or ``refuse`` when ``accept`` raises `Refuse`)
    and ``cancel`` (``inform``), keeps the subscribers, and `publish` sends an inform to
    each (or to those a predicate picks). ``accept(message)`` may be sync or async; what
    it returns is kept as `Subscriber.data` (a parsed filter, say).
    """

    def __init__(
        self,
        agent: Agent,
        *,
        ontology: str | None = None,
        accept: Callable[[ACLMessage], Any] | None = None,
    ) -> None:
        self.agent = agent
        self.ontology = ontology
        self._accept = accept
        self.subscribers: dict[tuple[str, str], Subscriber] = {}
        self._removers = [
            agent.add_handler(MessageTemplate(P.SUBSCRIBE, ontology=ontology), self._on_subscribe),
            agent.add_handler(
                MessageTemplate(P.CANCEL, ontology=ontology, where=self._is_ours), self._on_cancel
            ),
        ]

    def __len__(self) -> int:
        return len(self.subscribers)

    def _is_ours(self, message: ACLMessage) -> bool:
        return (message.sender, message.conversation_id or "") in self.subscribers

    async def _on_subscribe(self, message: ACLMessage) -> None:
        if message.conversation_id is None:
            await self.agent.reply(message, P.REFUSE, "a subscribe needs a conversation_id")
            return
        data = None
        if self._accept is not None:
            try:
                data = self._accept(message)
                if inspect.isawaitable(data):
                    data = await data
            except Refuse as exc:
                await self.agent.reply(message, P.REFUSE, exc.content)
                return
            except Failure as exc:
                await self.agent.reply(message, P.FAILURE, exc.content)
                return
        self.subscribers[(message.sender, message.conversation_id)] = Subscriber(message, data)
        await self.agent.reply(message, P.AGREE)

    async def _on_cancel(self, message: ACLMessage) -> None:
        self.subscribers.pop((message.sender, message.conversation_id or ""), None)
        await self.agent.reply(message, P.INFORM, "cancelled")

    async def publish(
        self, content: Any, *, where: Callable[[Subscriber], bool] | None = None
    ) -> int:
        """Send ``content`` in an inform to every subscriber (``where`` picks); how many got it."""
        sent = 0
        for key, sub in list(self.subscribers.items()):
            if where is not None and not where(sub):
                continue
            try:
                await self.agent.reply(sub.message, P.INFORM, content)
                sent += 1
            except Exception:
                log.exception("%s: informing %s failed; subscription dropped", self.agent, key[0])
                self.subscribers.pop(key, None)
        return sent

    async def end(self, subscriber: str | None = None, *, reason: Any = None) -> None:
        """End the subscriptions of ``subscriber`` (agent id), or all: they get ``cancel``.

        With a ``reason`` they get ``failure`` instead (their stream raises Failed).
        """
        for key, sub in list(self.subscribers.items()):
            if subscriber is not None and key[0] != subscriber:
                continue
            del self.subscribers[key]
            try:
                await self.agent.reply(
                    sub.message, P.CANCEL if reason is None else P.FAILURE, reason
                )
            except Exception:
                log.exception("%s: telling %s the subscription ended", self.agent, key[0])

    def close(self) -> None:
        """Stop answering subscribe and cancel (subscribers are not told: see `end`)."""
        for remove in self._removers:
            remove()
        self.subscribers.clear()


# -- FIPA-Contract-Net ---------------------------------------------------------------


@dataclass(init=False, repr=False, eq=False)
class Proposal(Frozen):
    """A participant's answer to a cfp: who, what it proposes, and the propose message."""

    __slots__ = ("content", "message", "participant")
    participant: str
    content: JsonValue
    message: ACLMessage

    def __init__(self, participant: str, content: JsonValue, message: ACLMessage) -> None:
        object.__setattr__(self, "participant", participant)
        object.__setattr__(self, "content", content)
        object.__setattr__(self, "message", message)


@dataclass(init=False, repr=False, eq=False)
class ContractNetResult(Record):
    """How a contract net went: proposals, who refused, what was accepted, and the results."""

    __slots__ = (
        "accepted",
        "failures",
        "late",
        "no_answer",
        "no_result",
        "proposals",
        "refused",
        "results",
    )
    proposals: list[Proposal]
    refused: dict[str, ACLMessage]
    accepted: list[Proposal]
    results: dict[str, JsonValue]
    failures: dict[str, ACLMessage]
    no_answer: list[str]
    no_result: list[str]
    late: list[ACLMessage]

    def __init__(
        self,
        proposals: list[Proposal] | None = None,
        refused: dict[str, ACLMessage] | None = None,
        accepted: list[Proposal] | None = None,
        results: dict[str, JsonValue] | None = None,
        failures: dict[str, ACLMessage] | None = None,
        no_answer: list[str] | None = None,
        no_result: list[str] | None = None,
        late: list[ACLMessage] | None = None,
    ) -> None:
        self.proposals = [] if proposals is None else proposals
        self.refused = {} if refused is None else refused
        self.accepted = [] if accepted is None else accepted
        self.results = {} if results is None else results
        self.failures = {} if failures is None else failures
        self.no_answer = [] if no_answer is None else no_answer
        self.no_result = [] if no_result is None else no_result
        self.late = [] if late is None else late


def _accept_all(proposals: list[Proposal]) -> list[Proposal]:
    return proposals


async def contract_net(
    agent: Agent,
    participants: Iterable[str],
    content: Any = None,
    *,
    deadline: float,
    select: Callable[[list[Proposal]], Iterable[Proposal]] = _accept_all,
    ontology: str | None = None,
    language: str | None = "json",
    result_timeout: float = DEFAULT_TIMEOUT,
) -> ContractNetResult:
    """FIPA-Contract-Net: cfp to ``participants``, proposals until ``deadline`` s, then award.

    ``select`` picks the proposals to accept (default: all); the others are rejected.
    Proposals that come after the deadline are ignored (listed in ``late``). The accepted
    participants' informs (``results``) or failures are awaited up to ``result_timeout`` s.
    """
    who = list(dict.fromkeys(participants))
    result = ContractNetResult()
    if not who:
        return result
    loop = asyncio.get_running_loop()
    cfp = _opening(
        agent,
        P.CFP,
        FIPA_CONTRACT_NET,
        who,
        content,
        ontology=ontology,
        language=language,
        timeout=deadline,
    )
    with agent.conversation(cfp.conversation_id, peers=who) as conv:
        await conv.send(cfp)
        pending = set(who)
        cfp_deadline = loop.time() + deadline
        while pending:
            try:
                m = await conv.receive(deadline=cfp_deadline)
            except ReplyTimeout:
                break
            if m.sender not in pending:
                log.warning("%s: second answer from %s to cfp ignored", agent, m.sender)
                continue
            pending.discard(m.sender)
            if m.performative is P.PROPOSE:
                result.proposals.append(Proposal(m.sender, m.content, m))
            else:
                result.refused[m.sender] = m
        result.no_answer = [p for p in who if p in pending]

        chosen = list(select(list(result.proposals)))
        chosen_ids = {id(p) for p in chosen}
        for proposal in result.proposals:
            if id(proposal) in chosen_ids:
                result.accepted.append(proposal)
                answer = proposal.message.reply(
                    P.ACCEPT_PROPOSAL, proposal.content, sender=agent.aid
                )
                await conv.send(answer.model_copy(update={"reply_with": new_id("r")}))
            else:
                await agent.send(
                    proposal.message.reply(P.REJECT_PROPOSAL, proposal.content, sender=agent.aid)
                )

        waiting = {p.participant for p in result.accepted}
        result_deadline = loop.time() + result_timeout
        while waiting:
            try:
                m = await conv.receive(deadline=result_deadline)
            except ReplyTimeout:
                break
            if m.performative is P.PROPOSE:
                result.late.append(m)  # after the deadline: ignored
                log.info("%s: late proposal from %s ignored", agent, m.sender)
            elif m.sender not in waiting:
                log.warning("%s: %s from %s not expected now", agent, m.performative, m.sender)
            elif m.performative is P.INFORM:
                waiting.discard(m.sender)
                result.results[m.sender] = m.content
            else:
                waiting.discard(m.sender)
                result.failures[m.sender] = m
        result.no_result = [p.participant for p in result.accepted if p.participant in waiting]
        # Proposals already delivered but not read yet are late too.
        while conv.pending():
            try:
                m = await conv.receive(timeout=0)
            except ConversationError:
                break
            if m.performative is P.PROPOSE:
                result.late.append(m)
    return result


async def _ignore(message: ACLMessage) -> None:
    """A rejected proposal needs no answer."""


def on_cfp(ontology: str | None = None, *, concurrent: bool = False) -> Callable[[Any], Any]:
    """Declare a Contract-Net participant's bid: ``async def f(self, cfp) -> proposal content``.

    Raise `Refuse` to decline. A ``reject-proposal`` is then accepted silently unless an
    `on_reject_proposal` handler is declared.
    """
    template = MessageTemplate(P.CFP, ontology=ontology)
    reject = MessageTemplate(P.REJECT_PROPOSAL, ontology=ontology)
    return declare(
        RouteSpec(template, concurrent, make=lambda agent, f: _respond(agent, f, propose=True)),
        RouteSpec(reject, fallback=True, make=lambda agent, f: _ignore),
    )


def on_accept_proposal(
    ontology: str | None = None, *, concurrent: bool = False
) -> Callable[[Any], Any]:
    """Declare what a participant does once accepted: returns the inform content (the result).

    Raise `Failure` when it cannot be done.
    """
    template = MessageTemplate(P.ACCEPT_PROPOSAL, ontology=ontology)
    return declare(
        RouteSpec(template, concurrent, make=lambda agent, f: _respond(agent, f, can_refuse=False))
    )


def on_reject_proposal(ontology: str | None = None) -> Callable[[Any], Any]:
    """Declare what a participant does when its proposal is rejected (no answer is sent)."""
    return declare(RouteSpec(MessageTemplate(P.REJECT_PROPOSAL, ontology=ontology)))
