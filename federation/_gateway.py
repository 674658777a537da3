"""The Gateway Agent: the ACL face of the local DyKnow instance.

One agent (``gateway@<platform>`` by default) answers, in ontology ``dyknow`` with JSON
content (the mapping is `GatewayService`, ``federation/_gateway_service.py``):

* FIPA-Request ``{"action": "list-labels" | "create-stream" | "remove-stream" | "query",
  …}`` → ``inform`` with the result, or ``refuse`` with the reason (a remove-stream of
  another platform: only a stream one of its agents created, ``not_creator_refused``);
* FIPA-Query (query-ref) for ``query`` and ``list-labels``;
* FIPA-Subscribe ``{"label": …, "policy": {…}}`` → ``agree``, then one ``inform``
  ``{"label": …, "samples": [[value, valid s, available s], …]}`` per batch the core
  subscription (with that policy) emits, until the initiator cancels or the stream ends
  (then the initiator gets ``cancel``: a clean end).

It registers its service (type ``dyknow-gateway``) with the platform's Directory
Facilitator; protected by default, so other platforms reach it through the Interface
Agent only (a `FederationPlatform` makes it private unless its config opens it: local
labels never leave a platform). Labels under a ``reserved`` prefix (``import/``: what
other platforms stream here) are for this platform's agents only: a request from another
platform that would read, create or write one is refused, counted
(``gateway_stats.reserved_refused``) and audited; so is its request naming a label not
here (``unknown_label_refused``: a query of any kind, a create-stream's source, a
subscribe; the lane's plain read leaves it to `_perform`) or a create-stream whose output
is taken (``taken_label_refused``), and, whoever asks, a
create-stream whose output is no valid semantic label (``bad_label_refused``) or a
request beyond the limits (``limit_refused``: ``max_streams``, ``max_subscriptions``, all
askers together; ``max_streams_per_platform``, ``max_subscriptions_per_platform``, what
one other platform may hold of them, so that one member cannot take every slot).
Made private while a
request or subscribe of another platform waits in its mailbox (a sharing reload,
`GatewayAgent.set_visibility`), it refuses that message as the Interface Agent would have
("access denied"; ``gateway_stats.access_refused``, the platform's ``stats.denied``,
audited); made private, it ends the subscriptions of other platforms and removes the
streams they created here (`GatewayEnded`). A platform revoked (removed from the
Interface Agent's trust store) loses its subscriptions and the streams it created here
the same way, and what it asked that still waits in the mailbox is refused so too
(``untrusted``).
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import orjson

from agents import (
    FIPA_QUERY,
    FIPA_REQUEST,
    FIPA_SUBSCRIBE,
    LATER,
    MAX_MESSAGE_BYTES,
    ACLMessage,
    Agent,
    DirectoryEvent,
    HandedOver,
    MessageTemplate,
    Performative,
    Refuse,
    ServiceDescription,
    TrustStore,
    Visibility,
    call_in_loop,
    on,
    on_query,
    on_request,
    platform_of,
)
from agents.transports import Subscription as TransportSubscription
from dyknow_core import DyKnowError, DyKnowInstance, Subscription, UnknownLabelError

from ._gateway_service import (
    ONTOLOGY,
    GatewayRefusal,
    GatewayService,
    answer_to_json,
    check_limits,
    latest_answer_plain,
    plain_latest,
    samples_to_json,
)
from ._quote import quoted

log = logging.getLogger(__name__)

P = Performative
# an enum member read from its class is a lookup through the enum's machinery (~0.3 µs in
# 3.11, ~8x a global's): the members a plain read on zenoh's thread compares with, once
_PRIVATE, _QUERY_REF, _REQUEST = Visibility.PRIVATE, P.QUERY_REF, P.REQUEST

GATEWAY_SERVICE_TYPE = "dyknow-gateway"
"""The Directory Facilitator service type every Gateway Agent registers."""

# What an inform's content may take: the message limit less room for the ACL fields
# (identifiers, conversation id, ontology) around it.
_INFORM_BUDGET = MAX_MESSAGE_BYTES - 4096
# A label another platform names that is longer than any semantic label is named in a
# refusal by its first 64 characters (as a bad output label is, `check_semantic_label`):
# the refusal's audit record is kept in memory and written, and a whole label would make
# each record as large as the request that brought it
_NAMED_WHOLE, _NAMED_START = 256, 64


def _named(label: str) -> str:
    """``label`` as a refusal names it: whole, or its start and "…" if longer than any
    semantic label."""
    return label if len(label) <= _NAMED_WHOLE else label[:_NAMED_START] + "…"


@dataclass(slots=True)
class GatewayStats:
    """What a Gateway Agent has sent to its subscribers, and what it refused (counted and
    audited, ``stage: gateway``), by kind."""

    informs: int = 0
    samples: int = 0
    too_large: int = 0
    subscriptions: int = 0
    reserved_refused: int = 0
    bad_label_refused: int = 0
    access_refused: int = 0
    unknown_label_refused: int = 0
    taken_label_refused: int = 0
    limit_refused: int = 0
    not_created_refused: int = 0
    not_creator_refused: int = 0
    streams_removed: int = 0


class GatewayEnded(NamedTuple):
    """What `GatewayAgent.set_visibility` ended: (asker, label) of each subscription and
    of each created stream (its process removed); ``kept``: (creator, label, readers) of
    each created stream kept, as a process staying reads it (handed to this platform)."""

    subscriptions: list[tuple[str, str]]
    streams: list[tuple[str, str]]
    kept: list[tuple[str, str, list[str]]]


def _gateway_told(
    gone: GatewayEnded,
) -> list[tuple[str, str, str, str, str, str]]:
    """What a gateway's reload or a revocation ended or kept, as said and audited:
    (verdict, label, agent, its audit field, the line's words, what the audit record adds
    to them)."""
    told = [
        (
            "ended",
            label,
            subscriber,
            "subscriber",
            f"gateway subscription of {subscriber} to {label!r} ended",
            "",
        )
        for subscriber, label in gone.subscriptions
    ]
    told += [
        (
            "ended",
            label,
            asker,
            "creator",
            f"gateway stream {label!r} created by {asker} removed",
            "",
        )
        for asker, label in gone.streams
    ]
    told += [
        (
            "kept",
            label,
            asker,
            "creator",
            f"gateway stream {label!r} created by {asker} kept: read by {', '.join(readers)}",
            " (now this platform's)",
        )
        for asker, label, readers in gone.kept
    ]
    return told


class _Feed:
    """One FIPA-Subscribe being served: the subscribe message and its core subscription."""

    # a plain class, not a dataclass: generating a dataclass's methods costs ~0.4 ms of a
    # node's start, each; nothing compares or prints these
    __slots__ = ("cancelled", "label", "message", "sub")

    def __init__(self, message: ACLMessage, label: str, sub: Subscription) -> None:
        self.message = message
        self.label = label
        self.sub = sub
        self.cancelled = False

    @property
    def key(self) -> tuple[str, str]:
        return (self.message.sender, self.message.conversation_id or "")

    def stop(self) -> None:
        """No inform goes out after this (the pump checks the flag before each one)."""
        self.cancelled = True
        self.sub.close()


class GatewayAgent(Agent):
    """The ACL face of a DyKnow instance: list labels, create streams, query, subscribe.

    ``visibility`` is that of the ``dyknow-gateway`` service it registers (protected:
    other platforms through the Interface Agent only; public: listed in the global
    directory too). ``register=False`` leaves the Directory Facilitator alone. The
    subscriptions of a platform that leaves the federation (its presence token goes) are
    dropped with it (the streams it created stay: it may come back). A platform removed
    from the trust store of its platform's Interface Agent (revoked, `TrustStore.remove`)
    loses both: its subscriptions end, the streams it created here are removed (counted,
    audited, logged), as when the gateway goes private. Labels starting with one of
    ``reserved`` may be read, created or written by agents of this platform only.
    At most ``max_streams`` created streams and ``max_subscriptions`` subscriptions at
    once, whoever asked (this platform's agents too), and at most
    ``max_streams_per_platform`` / ``max_subscriptions_per_platform`` of them held by one
    other platform (this platform's own agents are not bound by these).
    """

    def __init__(
        self,
        instance: DyKnowInstance,
        *,
        name: str = "gateway",
        service_name: str = "dyknow",
        visibility: Visibility | str = Visibility.PROTECTED,
        register: bool = True,
        max_subscriptions: int = 1024,
        max_streams: int = 256,
        max_subscriptions_per_platform: int = 256,
        max_streams_per_platform: int = 64,
        reserved: Sequence[str] = ("import/",),
    ) -> None:
        check_limits(
            max_subscriptions=max_subscriptions,
            max_subscriptions_per_platform=max_subscriptions_per_platform,
        )
        super().__init__(name)
        self.reserved = tuple(p for p in reserved if p)
        self.instance = instance
        # it keeps who created each stream (`GatewayService.creators`)
        self.service = GatewayService(
            instance, max_streams=max_streams, max_streams_per_platform=max_streams_per_platform
        )
        self.service_name = service_name
        self.visibility = Visibility(visibility)
        self._register = register
        self.max_subscriptions = max_subscriptions
        self.max_subscriptions_per_platform = max_subscriptions_per_platform
        self.gateway_stats = GatewayStats()
        # every subscription served, by (subscriber, conversation): what one platform
        # holds is counted from it, so a subscription dropped any way frees its slot
        self._feeds: dict[tuple[str, str], _Feed] = {}
        self._presence: TransportSubscription[DirectoryEvent] | None = None
        self._unhook_trust: Callable[[], None] | None = None
        self._trust: TrustStore | None = None  # the Interface Agent's: whom it let in
        # a subclass may add handlers (matched first) or checks: its handlers decide all
        self._at_once = type(self) is GatewayAgent

    # -- lifecycle ----------------------------------------------------------------------

    def description(self) -> ServiceDescription:
        """The service this agent registers with its platform's Directory Facilitator."""
        return ServiceDescription(
            name=self.service_name,
            type=GATEWAY_SERVICE_TYPE,
            provider=self.aid,
            ontology=ONTOLOGY,
            protocols=[FIPA_REQUEST, FIPA_QUERY, FIPA_SUBSCRIBE],
            properties={"instance": self.instance.name},
            visibility=self.visibility,
        )

    async def setup(self) -> None:
        """Register the gateway service; follow platforms leaving to drop their feeds, and
        platforms revoked to drop what they hold here."""
        platform = self.platform
        if self._register and platform.df is not None:
            await platform.df.register(self.description())
        if platform.global_df is not None:
            self._presence = platform.global_df.watch()
            self.spawn(self._follow_platforms(self._presence), "platforms")
        trust = getattr(platform.channel, "trust", None)
        if isinstance(trust, TrustStore):
            self._trust = trust
            self._unhook_trust = trust.on_remove(self._trust_removed)

    async def teardown(self) -> None:
        """End every subscription: the initiators get ``failure`` (we stop, not the stream)."""
        if self._unhook_trust is not None:
            self._unhook_trust()
            self._unhook_trust = None
        if self._presence is not None:
            self._presence.close()
        for feed in list(self._feeds.values()):
            self._drop(feed)
            try:
                await self.reply(feed.message, P.FAILURE, f"{self.aid} stopped")
            except Exception as exc:
                log.debug("%s: telling %s we stop: %s", self, feed.message.sender, exc)

    async def set_visibility(self, visibility: Visibility | str, why: str) -> GatewayEnded:
        """Serve with ``visibility`` from now on: the service re-registered so (each
        request after it is let in or refused by it); made private, the subscriptions of
        other platforms end, their subscribers told ``failure`` with ``why``, then the
        streams they created here are removed (as their process removed by hand: this
        platform's subscribers to one see it end), but for one a staying process reads:
        kept, handed to this platform. Returns what ended and what was kept. A
        re-registration that fails leaves the gateway as it was (and raises)."""
        wanted = Visibility(visibility)
        platform = self.platform
        was = self.visibility
        # set before the await: a request already in the mailbox, handled meanwhile, is
        # let in or refused by the new setting (`_check_access`)
        self.visibility = wanted
        if self._register and platform.df is not None:
            try:
                await platform.df.modify(self.description())
            except BaseException:
                self.visibility = was
                raise
        ended = GatewayEnded([], [], [])
        if wanted is not Visibility.PRIVATE:
            return ended
        for feed in list(self._feeds.values()):
            subscriber = feed.message.sender
            if platform_of(subscriber) == platform.name:
                continue  # this platform's own agents may still use a private gateway
            self._drop(feed)
            ended.subscriptions.append((subscriber, feed.label))
            try:
                await self.reply(feed.message, P.FAILURE, why)
            except Exception as exc:  # it is ended here whether or not it hears so
                log.debug("%s: telling %s its subscription ended: %s", self, subscriber, exc)
        # After the subscriptions: another platform's subscriber to a created stream was
        # told `why` above, not "stream ended". The asker is told nothing more: its
        # create-stream conversation ended with the inform (a failure now would reach it
        # as a late or unsolicited answer).
        self._remove_created(lambda p: p != platform.name, ended)
        return ended

    def _remove_created(self, of: Callable[[str], bool], ended: GatewayEnded) -> None:
        """Remove the streams created here by the platforms ``of`` holds true for, but for
        one a staying process reads (kept, handed to this platform); into ``ended``."""
        creators = self.service.creators
        theirs = {o: a for o, a in creators.items() if of(platform_of(a))}
        # one a staying process reads (this platform's built on it) would leave that one
        # without input: it is kept, handed to this platform (not considered again, and
        # no longer counted in its creator's max_streams_per_platform)
        read_on = self.service.read_on(theirs)
        for output, asker in theirs.items():
            if output in read_on:
                creators[output] = self.aid
                ended.kept.append((asker, output, read_on[output]))
                continue
            if self.service.remove(output):
                self.gateway_stats.streams_removed += 1
                ended.streams.append((asker, output))

    def _trust_removed(self, revoked: str) -> None:
        """The trust store's callback: revoke now when called in this agent's event loop,
        else in it, soon (the instance is that loop's)."""
        call_in_loop(self._loop, self._revoke, revoked)

    def _revoke(self, revoked: str) -> GatewayEnded:
        """``revoked`` is no member any more (removed from the trust file): its
        subscriptions end and the streams it created here are removed, as when the
        gateway goes private (but for one a staying process reads: kept); counted,
        audited (``code: untrusted``) and logged. It is told nothing: nothing it is sent
        should reach it any more (a live session would still seal for it)."""
        ended = GatewayEnded([], [], [])
        if self._unhook_trust is None or revoked == self.platform.name:
            return ended  # stopped meanwhile; or this platform's own: never its own streams
        for feed in list(self._feeds.values()):
            if platform_of(feed.message.sender) == revoked:
                self._drop(feed)
                ended.subscriptions.append((feed.message.sender, feed.label))
        self._remove_created(lambda p: p == revoked, ended)
        why = f"platform {revoked!r} was removed from the trust file (revoked)"
        told = _gateway_told(ended)
        for verdict, label, agent, role, what, more in told:
            self.platform.audit(
                verdict=verdict,
                stage="trust",
                code="untrusted",
                stream=label,
                to=platform_of(agent),
                **{role: agent},
                reason=f"{what}{more}: {why}",
            )
        if told:
            log.warning("%s: %s: %s", self, why, "; ".join(what for *_, what, _ in told))
        return ended

    @property
    def subscriptions(self) -> dict[tuple[str, str], str]:
        """The subscriptions served now: (subscriber, conversation id) → label."""
        return {key: feed.label for key, feed in self._feeds.items()}

    # -- FIPA-Request and FIPA-Query ----------------------------------------------------

    def _perform(self, content: Any, message: ACLMessage) -> dict[str, Any]:
        remote = platform_of(message.sender) != self.platform.name
        if remote:
            self._check_access(message)
            self._check_reserved(message, content)
        action = content.get("action") if isinstance(content, dict) else None
        # who created the stream a remove-stream names: the service forgets it
        label = content.get("label") if action == "remove-stream" else None
        creator = self.service.creators.get(label, "") if isinstance(label, str) else ""
        try:
            result = self.service.perform(content, message.sender, limited=remote)
        except GatewayRefusal as exc:
            told = self._told(exc, message)
            if exc.code is not None:
                self._counted(message, exc.code, told)
            raise Refuse(told) from exc
        if remote and action == "list-labels":
            result = {"labels": [lb for lb in result["labels"] if not self._is_reserved(lb)]}
        elif action == "remove-stream":
            self._removed(message, creator or self.aid, result)
        return result

    def _removed(self, message: ACLMessage, creator: str, result: dict[str, Any]) -> None:
        """Count, audit and log a created stream ended (or kept, handed to this platform)
        at ``message``'s asking: one record, as a reload's or a revocation's."""
        asker = message.sender
        if "removed" in result:
            self.gateway_stats.streams_removed += 1
            told = _gateway_told(GatewayEnded([], [(creator, result["removed"])], []))
        else:
            readers = self.service.read_on([result["kept"]]).get(result["kept"], [])
            told = _gateway_told(GatewayEnded([], [], [(creator, result["kept"], readers)]))
        for verdict, label, agent, role, what, more in told:
            self.platform.audit(
                verdict=verdict,
                stage="gateway",
                code="remove-stream",
                stream=label,
                to=platform_of(agent),
                sender=asker,
                **{"from": platform_of(asker), role: agent},
                reason=f"{what}{more}: asked by {asker}",
            )
            log.info("%s: %s%s: asked by %s", self, what, more, asker)

    def _counted(self, message: ACLMessage, code: str, reason: str) -> None:
        """Count and audit a refusal of the service's by its code: a bad label or a limit
        whoever asks; a label not here, or a create-stream's output taken, when another
        platform asks (both tell it which labels exist; this platform's own agents may
        look for one not published yet)."""
        stats = self.gateway_stats
        if code == "bad-label":
            stats.bad_label_refused += 1
        elif code in ("unknown-label", "label-taken"):
            if platform_of(message.sender) == self.platform.name:
                return
            if code == "unknown-label":
                stats.unknown_label_refused += 1
            else:
                stats.taken_label_refused += 1
        elif code in ("stream-limit", "subscription-limit"):
            stats.limit_refused += 1
        elif code == "not-creator":  # never this platform's own: they may remove any
            stats.not_creator_refused += 1
        elif code == "not-created":
            if platform_of(message.sender) == self.platform.name:
                return  # as a label not here: this platform's agents are not audited
            stats.not_created_refused += 1
        else:
            return
        self._audit_refusal(message, code, reason)

    def _told(self, refusal: GatewayRefusal, message: ACLMessage) -> str:
        """The refusal's reason as ``message``'s sender may read it.

        An unknown label's reason lists labels that exist: to another platform, only
        those it may see (reserved ones are not even named, as in list-labels), and the
        asked label itself cut if it is longer than any semantic label (`_named`).
        """
        cause = refusal.__cause__
        if isinstance(cause, UnknownLabelError) and platform_of(message.sender) != (
            self.platform.name
        ):
            seen = [lb for lb in self.instance.labels() if not self._is_reserved(lb)]
            return str(UnknownLabelError(_named(cause.label), seen))
        return refusal.reason

    def _is_reserved(self, label: Any) -> bool:
        return isinstance(label, str) and label.startswith(self.reserved)

    def _check_reserved(self, message: ACLMessage, content: Any) -> None:
        """Refuse (count, audit) another platform's request naming a reserved label."""
        if not isinstance(content, dict):
            return
        reserved = self.reserved
        for key in ("label", "output"):
            label = content.get(key)
            # `_is_reserved`, inline: every request from another platform passes here
            if isinstance(label, str) and label.startswith(reserved):
                prefix = next(p for p in self.reserved if label.startswith(p))
                reason = (
                    f"label {_named(label)!r} is reserved (prefix {prefix!r}: streams other "
                    "platforms send here): only agents of this platform may read, create "
                    "or write it"
                )
                self.gateway_stats.reserved_refused += 1
                self._audit_refusal(message, "reserved-label", reason)
                raise Refuse(reason)

    def _check_access(self, message: ACLMessage) -> None:
        """Refuse (count, audit) a message of another platform the gateway's visibility
        no longer allows, or of a platform revoked since: the Interface Agent let it in,
        by the visibility and the trust of then.

        A request or subscribe may wait in the mailbox while a reload makes the gateway
        private, or while its platform is revoked; served, it would open a private gateway
        to another platform, or create for a revoked one what its revocation removed.
        """
        sender = platform_of(message.sender)
        trust = self._trust
        if trust is not None and sender not in trust:
            code = "untrusted"
            reason = f"platform {sender!r} is not in the trust file (revoked)"
        # as `visibility_allows` rules for a message that came through the Interface Agent
        elif self.visibility is Visibility.PRIVATE:
            code = "access-denied"
            reason = f"access denied: {self.aid} offers no service that platform {sender!r} may use"
        else:
            return
        self.gateway_stats.access_refused += 1
        self.platform.stats.denied += 1
        self._audit_refusal(message, code, reason)
        raise Refuse(reason)

    def _audit_refusal(self, message: ACLMessage, code: str, reason: str) -> None:
        """Record a refused request in the platform's audit log: one by one within the
        asking platform's budget, the rest summed up (`AgentPlatform.audit_refused`)."""
        self.platform.audit_refused(message, "gateway", code, reason)

    def _plain_latest_label(self, message: ACLMessage) -> str | None:
        """The label a plain query for its latest sample asks, if answerable at once; else None.

        None for a private gateway, another ontology or performative, any other action,
        or a reserved label: `_on_request` / `_on_query` decide, count and audit those.
        """
        # a message holds every field in its __dict__: a dict lookup each, not a pass
        # through pydantic's attribute hook (the lane's answers read here)
        fields = message.__dict__
        performative = fields["performative"]
        if not self._at_once or fields["ontology"] != ONTOLOGY or self.visibility is _PRIVATE:
            return None
        content = fields["content"]
        if performative is _QUERY_REF:
            if type(content) is not dict:
                return None
            content = {"action": "query", **content}
        elif performative is not _REQUEST:
            return None
        label = plain_latest(content)
        if label is None or label.startswith(self.reserved):
            return None
        return label

    def answer_at_once(self, message: ACLMessage) -> Any:
        """Another platform's query for a label's latest sample, answered as it comes.

        What `_on_request` / `_on_query` answer to it, without the mailbox and a task;
        anything else, and whatever they would refuse (a private gateway, a reserved
        label, a label not here), is `LATER`: they decide, count and audit it.
        """
        label = self._plain_latest_label(message)
        if label is None:
            return LATER
        try:
            return answer_to_json(self.instance.latest(label))
        except Exception:
            return LATER

    def answer_on_thread(self, message: ACLMessage) -> Any:
        """`answer_at_once` on zenoh's thread: the label's latest sample as `Cache.extend` keeps
        it (`DyKnowInstance.latest_now`), or `LATER` (the loop's `answer_at_once` decides).

        Handed over to its reply (`HandedOver`, no copy) when it is plain JSON: its dicts
        and list are made here and kept nowhere else, the label is a str (`plain_latest`).
        """
        label = self._plain_latest_label(message)
        if label is None:
            return LATER
        read = self.instance.latest_now(label)
        if read is None:
            return LATER
        answer, plain = latest_answer_plain(label, *read)  # `answer_to_json`'s, of that row
        return HandedOver(answer) if plain else answer

    @on_request(ONTOLOGY)
    async def _on_request(self, message: ACLMessage) -> Any:
        """list-labels, create-stream, remove-stream, query: the result, or refuse with the
        reason."""
        return self._perform(message.content, message)

    @on_query(ONTOLOGY)
    async def _on_query(self, message: ACLMessage) -> Any:
        """query-ref for ``query`` (the default action) and ``list-labels``."""
        if message.performative is P.QUERY_IF:
            raise Refuse("the gateway answers query-ref, not query-if")
        content = message.content
        if isinstance(content, dict):
            content = {"action": "query", **content}
            if content["action"] in ("create-stream", "remove-stream"):
                action = content["action"]
                raise Refuse(f"{action} is an action: ask for it with FIPA-Request")
        return self._perform(content, message)

    # -- FIPA-Subscribe -----------------------------------------------------------------

    @on(MessageTemplate(P.SUBSCRIBE, ontology=ONTOLOGY))
    async def _on_subscribe(self, message: ACLMessage) -> None:
        """Agree and start informing, or refuse (unknown label, bad policy) with the reason."""
        remote = platform_of(message.sender) != self.platform.name
        reason = None
        if remote:
            try:
                self._check_access(message)
            except Refuse as exc:
                reason = str(exc.content)
        if reason is None:
            reason = self._subscribe_problem(message)
        if reason is None and remote:
            try:
                self._check_reserved(message, message.content)
            except Refuse as exc:
                reason = str(exc.content)
        if reason is not None:
            await self.reply(message, P.REFUSE, reason)
            return
        try:
            label, policy = self.service.subscription_policy(message.content)
            sub = self.instance.subscribe(label, policy)
        except GatewayRefusal as exc:
            told = self._told(exc, message)
            if exc.code is not None:
                self._counted(message, exc.code, told)
            await self.reply(message, P.REFUSE, told)
            return
        except (DyKnowError, OverflowError) as exc:
            await self.reply(message, P.REFUSE, str(exc))
            return
        feed = _Feed(message, label, sub)
        self._feeds[feed.key] = feed
        self.gateway_stats.subscriptions += 1
        try:
            await self.reply(message, P.AGREE)
        except BaseException:
            self._drop(feed)
            raise
        # Started only now: no inform may overtake the agree.
        self.spawn(self._pump(feed), f"feed[{label}]")

    def _subscribe_problem(self, message: ACLMessage) -> str | None:
        if message.conversation_id is None:
            return "a subscribe needs a conversation_id"
        if (message.sender, message.conversation_id) in self._feeds:
            # the asker's id, echoed on one line and bounded (as `quoted` bounds any)
            conv = quoted(message.conversation_id, _NAMED_START)
            return f"conversation {conv} already has a subscription"
        platform = platform_of(message.sender)
        if platform != self.platform.name:
            limit = self.max_subscriptions_per_platform
            if self.held_by(platform) >= limit:
                reason = f"too many subscriptions for {platform} (limit {limit} per platform)"
                self._counted(message, "subscription-limit", reason)
                return reason
        if len(self._feeds) >= self.max_subscriptions:
            reason = f"too many subscriptions (limit {self.max_subscriptions})"
            self._counted(message, "subscription-limit", reason)
            return reason
        return None

    def held_by(self, platform: str) -> int:
        """How many of the subscriptions served now ``platform``'s agents hold."""
        return sum(1 for key in self._feeds if platform_of(key[0]) == platform)

    @on(MessageTemplate(P.CANCEL, ontology=ONTOLOGY))
    async def _on_cancel(self, message: ACLMessage) -> None:
        """The initiator ends its subscription: close the core subscription, confirm."""
        feed = self._feeds.get((message.sender, message.conversation_id or ""))
        if feed is None:
            conv = quoted(message.conversation_id, _NAMED_START)
            await self.reply(message, P.FAILURE, f"no subscription in conversation {conv}")
            return
        self._drop(feed)
        await self.reply(message, P.INFORM, "cancelled")

    @on(MessageTemplate((P.FAILURE, P.NOT_UNDERSTOOD), ontology=ONTOLOGY))
    async def _on_trouble(self, message: ACLMessage) -> None:
        """An inform bounced (the subscriber is gone, or refused it): stop feeding it."""
        feed = self._feeds.get((message.sender, message.conversation_id or ""))
        if feed is not None:
            # the subscriber's word on why: bounded, one line
            log.info(
                "%s: subscription of %s to %r dropped: %s",
                self,
                message.sender,
                feed.label,
                quoted(message.content),
            )
            self._drop(feed)
        else:
            log.debug("%s: %s from %s ignored", self, message.performative, message.sender)

    def _drop(self, feed: _Feed) -> None:
        feed.stop()
        if self._feeds.get(feed.key) is feed:
            del self._feeds[feed.key]

    async def _pump(self, feed: _Feed) -> None:
        """Inform the subscriber of each batch until cancelled or the stream ends."""
        try:
            async for batch in feed.sub.batches():
                if feed.cancelled:
                    return
                await self._inform(feed, samples_to_json(batch))
        except Exception:
            log.exception("%s: informing %s failed; subscription dropped", self, feed.key[0])
            self._drop(feed)
            return
        if feed.cancelled:
            return
        # The stream ended (its process was removed, or the policy's end passed).
        self._drop(feed)
        await self.reply(feed.message, P.CANCEL, f"stream {feed.label!r} ended")

    async def _inform(self, feed: _Feed, rows: list[list[Any]]) -> None:
        """Send ``rows`` in as few informs as the message size limit allows."""
        stats = self.gateway_stats
        pending = [rows]
        while pending:
            part = pending.pop()
            content = {"label": feed.label, "samples": part}
            try:
                size = len(orjson.dumps(content))
            except orjson.JSONEncodeError:
                size = -1  # e.g. an integer beyond 64 bits: only this row may be lost
            if 0 <= size <= _INFORM_BUDGET:
                if feed.cancelled:
                    return
                await self.reply(feed.message, P.INFORM, content)
                stats.informs += 1
                stats.samples += len(part)
            elif len(part) > 1:
                mid = len(part) // 2
                pending.append(part[mid:])
                pending.append(part[:mid])
            else:
                stats.too_large += 1
                log.warning(
                    "%s: a sample of %r cannot be sent as JSON within %d bytes; skipped",
                    self,
                    feed.label,
                    _INFORM_BUDGET,
                )

    async def _follow_platforms(self, events: TransportSubscription[DirectoryEvent]) -> None:
        """A platform that leaves takes its subscriptions with it."""
        async for event in events:
            if event.op != "platform-gone":
                continue
            suffix = f"@{event.platform}"
            for feed in list(self._feeds.values()):
                if feed.key[0].endswith(suffix):
                    log.info("%s: %s left; its subscription ended", self, event.platform)
                    self._drop(feed)
