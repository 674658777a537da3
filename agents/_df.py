"""The Directory Facilitator: who provides which service, local and federation-wide.

Each platform runs a `DirectoryFacilitator` agent (``df@<platform>``) holding the
services of its agents. It answers FIPA-Request ``register`` / ``deregister`` /
``modify`` / ``search`` and FIPA-Subscribe (ontology ``fipa-agent-management``), and
has the same operations as Python methods for local code.

Visibility: *public* services are visible to every platform; *protected* ones to this
platform's agents directly and to other platforms only through the Interface Agent;
*private* ones never leave the platform. `visibility_allows` is the one rule, used by
searches and by the Interface Agent's access control (with `DirectoryFacilitator.reachable`).

The global directory is distributed (``docs/wire.md``): each DF serves its public
services on ``dyknow/<fed>/v1/df/<platform>`` and publishes their changes on
``…/df-events/<platform>``, both as directory statements signed with the platform's key
(`DirectoryAuth`); a `GlobalDirectory` on every platform builds its view from a query of
``…/df/*``, follows the events, and watches presence ``…/alive/*``: the entries of a
platform whose token goes (it crashed, was killed, left) disappear, and watchers get a
``platform-gone`` event naming it. With a trust file only what trusted platforms signed
counts (``docs/security.md``, "Membership and the directory").
"""

# Annotations are evaluated here, not kept as strings (no ``from __future__ import
# annotations``): the node imports this module, and pydantic and typing would compile
# each string at every start. A name defined later or only for type checking is quoted.
import asyncio
import base64
import binascii
import contextlib
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterable
from enum import StrEnum
from typing import TYPE_CHECKING, Annotated, Any, NamedTuple

import orjson
from pydantic import BaseModel, ConfigDict, Field, JsonValue, ValidationError

from ._acl import WIRE_VERSION, ACLMessage, AgentIdStr, Performative, platform_of
from ._agent import Agent
from ._aio import Pending, together
from ._bucket import TokenBucket
from ._dfgate import DEFAULT_DF_EVENT_LIMIT, DfEventGate, DfEventLimit
from ._directory_auth import DirectoryAuth, DirectoryStatementError, Statement, make_nonce
from ._exceptions import AgentError, ServiceError, TransportError
from ._gate import shed_counts
from ._presence import PRESENCE_BURST, PRESENCE_RATE, presence_bucket
from ._protocols import (
    DEFAULT_TIMEOUT,
    Publisher,
    Refuse,
    SubscriptionStream,
    on_request,
    request,
    subscribe,
)
from ._tally import Tally, since
from .transports import Handle, Inbox, Message, Presence, Reply, Subscription, Transport

if TYPE_CHECKING:
    from ._platform import AgentPlatform
    from ._security import KeyPair, TrustStore

log = logging.getLogger(__name__)

FIPA_AGENT_MANAGEMENT = "fipa-agent-management"

DF_QUERY_RATE = 50.0
"""Global-directory queries per second (bursts as many) answered; the rest are shed."""
MAX_DF_SUBSCRIPTIONS = 16
"""Directory subscriptions one other platform may hold here (each is told of every change)."""

_Name = Annotated[str, Field(min_length=1, max_length=200)]


def _no_items() -> list[Any]:
    """A new empty list: the default of a list field.

    Not ``list`` itself: pydantic reads a builtin's signature by tokenizing its text, and
    the first time compiles the tokenizer's expressions (~6 ms of a node's start).
    """
    return []


class Visibility(StrEnum):
    """Who may see and use a service."""

    PUBLIC = "public"
    PROTECTED = "protected"
    PRIVATE = "private"


class ServiceDescription(BaseModel):
    """A service: its name and type, the agent providing it, properties, visibility.

    A provider's services are told apart by name: (provider, name) is the key.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)

    name: _Name
    type: _Name
    provider: AgentIdStr
    properties: dict[str, JsonValue] = Field(default_factory=dict)
    ontology: str | None = None
    protocols: list[str] = Field(default_factory=_no_items)
    visibility: Visibility = Visibility.PRIVATE

    @property
    def platform(self) -> str:
        """The platform of the provider."""
        return platform_of(self.provider)

    @property
    def key(self) -> tuple[str, str]:
        """(provider, name): what identifies the service."""
        return (self.provider, self.name)

    def to_obj(self) -> dict[str, Any]:
        """The service as a JSON object."""
        return self.model_dump(mode="json", exclude_none=True)


class ServiceQuery(BaseModel):
    """A search: every field set must match; ``properties`` must be a subset of the service's."""

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)

    name: str | None = None
    type: str | None = None
    provider: str | None = None
    ontology: str | None = None
    protocol: str | None = None
    properties: dict[str, JsonValue] = Field(default_factory=dict)

    def matches(self, service: ServiceDescription) -> bool:
        """Whether ``service`` answers this query."""
        if self.name is not None and service.name != self.name:
            return False
        if self.type is not None and service.type != self.type:
            return False
        if self.provider is not None and service.provider != self.provider:
            return False
        if self.ontology is not None and service.ontology != self.ontology:
            return False
        if self.protocol is not None and self.protocol not in service.protocols:
            return False
        props = service.properties
        return all(k in props and props[k] == v for k, v in self.properties.items())


def _query(query: object, fields: dict[str, Any]) -> ServiceQuery:
    """A query from a ServiceQuery, a JSON object or None, plus keyword fields (validated)."""
    if isinstance(query, ServiceQuery):
        query = query.model_dump(exclude_defaults=True)
    if query is None:
        query = {}
    if isinstance(query, dict):
        query = {**query, **fields}
    return ServiceQuery.model_validate(query)


_MAX_REACH = 4096  # `reachable`'s remembered answers: (provider here, asking platform) pairs


def visibility_allows(
    service: ServiceDescription, asker_platform: str, via_interface: bool
) -> bool:
    """Whether an agent of ``asker_platform`` may see/use ``service``.

    Agents of the provider's platform may use everything; other platforms public
    services, and protected ones only when the message came through the Interface Agent
    (``via_interface``); private services never.
    """
    if asker_platform == platform_of(service.provider):
        return True
    if service.visibility is Visibility.PUBLIC:
        return True
    return service.visibility is Visibility.PROTECTED and via_interface


class DirectoryEvent(NamedTuple):
    """A change in a directory, as its watchers see it.

    ``op`` is ``register``, ``deregister`` or ``modify`` (of ``service``), or, in the
    global view only, ``platform-up`` / ``platform-gone`` (``service`` is None).
    """

    op: str
    platform: str
    service: ServiceDescription | None


_OPS = frozenset({"register", "deregister", "modify"})


def _seen_as(
    op: str,
    old: ServiceDescription | None,
    new: ServiceDescription | None,
    visible: Callable[[ServiceDescription], bool],
) -> tuple[str, ServiceDescription] | None:
    """How a change looks to someone who sees only ``visible`` services (or None: not at all)."""
    was = old is not None and visible(old)
    now = new is not None and visible(new)
    if was and now:
        assert new is not None
        return (op if op != "register" else "modify", new)
    if now:
        assert new is not None
        return ("register", new)
    if was:
        assert old is not None
        return ("deregister", old)
    return None


def _is_public(service: ServiceDescription) -> bool:
    return service.visibility is Visibility.PUBLIC


def _watch(watchers: list[Inbox[DirectoryEvent]], maxlen: int) -> Subscription[DirectoryEvent]:
    inbox: Inbox[DirectoryEvent] = Inbox(asyncio.get_running_loop(), maxlen)
    watchers.append(inbox)

    def remove() -> None:
        if inbox in watchers:
            watchers.remove(inbox)

    return Subscription(inbox, remove)


class DirectoryFacilitator(Agent):
    """The local DF: services of this platform's agents, searchable and watchable.

    Python API (local, trusted code): `register`, `deregister`, `modify`, `search`,
    `watch`; the Interface Agent uses `services_of_agent`, `service_of_agent` and
    `reachable`. ACL API: FIPA-Request with ontology ``fipa-agent-management`` and
    content ``{"action": "register"|"modify", "service": {…}}``,
    ``{"action": "deregister", "name": …}`` (``name`` left out: all the sender's),
    ``{"action": "search", "query": {…}, "scope": "local"|"global"}`` (answers a list of
    services); an agent registers, modifies and deregisters only its own services.
    FIPA-Subscribe with a query as content: informs ``{"op": …, "service": {…}}``.
    """

    def __init__(self, name: str = "df") -> None:
        super().__init__(name)
        self._services: dict[str, dict[str, ServiceDescription]] = {}
        # `reachable`'s answers, asked for every request from another platform; emptied
        # whenever a service is registered, modified or removed
        self._reach: dict[tuple[str, str, bool], bool] = {}
        self._watchers: list[Inbox[DirectoryEvent]] = []
        self._subscriptions = Publisher(
            self, ontology=FIPA_AGENT_MANAGEMENT, accept=self._accept_subscriber
        )
        self._queryable: Handle | None = None
        self._left = False
        # platforms that said, signed, that they left and were not listed again since:
        # none of our agents is reachable for them (`reachable`)
        self._said_left: set[str] = set()
        # directory queries are screened on the transport's thread: anyone on the network
        # may ask, and a flood would otherwise cost the event loop a task each
        self._query_lock = threading.Lock()
        self._query_bucket = TokenBucket(DF_QUERY_RATE, DF_QUERY_RATE, time.monotonic())
        self.queries_shed = 0  # directory queries dropped unanswered, since start
        self.queries_refused = 0  # let through, but not a query (audited: `_refuse_query`)
        self.subscriptions_refused = 0  # subscribes of other platforms over their limit
        self._shed_pending = Pending(1.0)  # shed since the last audit record

    async def setup(self) -> None:
        """Serve this platform's public services to the global directory."""
        key = self.platform.key("df")
        self._queryable = self.platform.declared(
            await self.platform.transport.serve(key, self._serve_public, admit=self._admit_query),
            f"directory queryable {key}",
            "other platforms can no longer find this platform's agents (their directory "
            "queries go unanswered)",
        )
        self.spawn(self._report_shed(), "df.shed-report")

    def _admit_query(self, payload: bytes) -> bool:
        """Whether a directory query is answered (called on the transport's thread)."""
        with self._query_lock:
            if self._query_bucket.take(time.monotonic()):
                return True
            self.queries_shed += 1
        self._shed_pending.add()
        return False

    def _refuse_query(self, reason: str) -> None:
        """Count a directory query refused unanswered; audit it within the channel's budget."""
        self.queries_refused += 1
        # anyone may query: the channel bounds the records of unauthenticated input
        audit = getattr(self.platform.channel, "audit_unauthenticated", None)
        if audit is not None:
            audit(None, f"malformed: {reason}", "df")

    async def _report_shed(self) -> None:
        """Audit the directory queries shed, summed up, at most once per second."""
        while True:
            n = await self._shed_pending.take()  # asleep while nothing is shed
            if n:
                self.platform.audit(
                    verdict="dropped",
                    stage="df-shed",
                    count=n,
                    reason=(
                        f"directory queries shed: {n} dropped unanswered before the event "
                        f"loop (over {DF_QUERY_RATE:g}/s, bursts of {DF_QUERY_RATE:g})"
                    ),
                )

    async def teardown(self) -> None:
        """End subscriptions and watches, stop serving."""
        await self._subscriptions.end()
        for inbox in self._watchers:
            inbox.close()
        self._watchers.clear()
        if self._queryable is not None:
            try:
                await self._queryable.aclose()
            except Exception as exc:  # the transport may be gone already
                log.debug("%s: undeclaring the queryable: %s", self, exc)

    # -- Python API -------------------------------------------------------------------

    def _get(self, provider: str, name: str) -> ServiceDescription | None:
        return self._services.get(provider, {}).get(name)

    def _check_local(self, service: ServiceDescription) -> None:
        if service.platform != self.platform.name:
            raise ServiceError(
                f"{service.provider} is not an agent of platform {self.platform.name}"
            )

    async def register(self, service: ServiceDescription) -> ServiceDescription:
        """Add ``service``; ServiceError when its provider is not local or it exists."""
        self._check_local(service)
        if self._get(*service.key) is not None:
            raise ServiceError(f"{service.provider} already registered {service.name!r}")
        self._services.setdefault(service.provider, {})[service.name] = service
        self._reach.clear()
        await self._changed("register", None, service)
        return service

    async def modify(self, service: ServiceDescription) -> ServiceDescription:
        """Replace the registered service with the same (provider, name).

        If telling the change fails (or is cancelled), the old entry is restored and the
        error raised: a caller told of the failure may take the entry to be as it was. Those
        already told of the new one (watchers, subscribers) are not told of the revert.
        """
        self._check_local(service)
        old = self._get(*service.key)
        if old is None:
            raise ServiceError(f"{service.provider} has no service {service.name!r}")
        self._services[service.provider][service.name] = service
        self._reach.clear()
        try:
            await self._changed("modify", old, service)
        except BaseException:
            mine = self._services.get(service.provider)
            if mine is not None and mine.get(service.name) is service:  # not changed since
                mine[service.name] = old
                self._reach.clear()
            raise
        return service

    async def deregister(self, provider: str, name: str | None = None) -> list[ServiceDescription]:
        """Remove ``provider``'s service ``name`` (all of them when None); what was removed."""
        removed = self._remove(provider, name)
        for service in removed:
            await self._changed("deregister", service, None)
        return removed

    def _remove(self, provider: str, name: str | None) -> list[ServiceDescription]:
        mine = self._services.get(provider)
        if not mine:
            return []
        self._reach.clear()
        if name is None:
            removed = list(mine.values())
            mine.clear()
        else:
            one = mine.pop(name, None)
            removed = [] if one is None else [one]
        if not mine:
            self._services.pop(provider, None)
        return removed

    def forget_agent(self, agent: str) -> None:
        """Deregister every service of an agent that stopped (called by the platform)."""
        removed = self._remove(agent, None)
        if removed and self.running:
            self.spawn(self._announce_removed(removed), "forget")
        else:
            for service in removed:
                self._tell_watchers("deregister", service)

    async def _announce_removed(self, removed: list[ServiceDescription]) -> None:
        for service in removed:
            await self._changed("deregister", service, None)

    def search(
        self,
        query: ServiceQuery | dict[str, Any] | None = None,
        *,
        asker_platform: str | None = None,
        via_interface: bool = False,
        **fields: Any,
    ) -> list[ServiceDescription]:
        """The services matching ``query`` (or keyword fields) that the asker may see.

        ``asker_platform`` None means a local asker: every service is visible.
        """
        q = _query(query, fields)
        found = []
        for services in self._services.values():
            for service in services.values():
                if q.matches(service) and (
                    asker_platform is None
                    or visibility_allows(service, asker_platform, via_interface)
                ):
                    found.append(service)
        return found

    def services(self) -> list[ServiceDescription]:
        """Every service registered here."""
        return [s for services in self._services.values() for s in services.values()]

    def services_of_agent(self, agent: str) -> list[ServiceDescription]:
        """The services ``agent`` (``name@platform``) provides here (O(1): per-message use)."""
        return list(self._services.get(agent, {}).values())

    def service_of_agent(self, agent: str, name: str) -> ServiceDescription | None:
        """``agent``'s service called ``name``, if registered."""
        return self._get(agent, name)

    def reachable(self, receiver: str, asker_platform: str, *, via_interface: bool = True) -> bool:
        """Whether an agent of ``asker_platform`` may send to local agent ``receiver``.

        True when ``receiver`` provides at least one service the asker may use
        (`visibility_allows`); the DF itself is always reachable, for searches. Never for
        a platform that said, signed, that it left, until it is listed again (`said_left`).
        """
        if asker_platform in self._said_left:
            return False
        key = (receiver, asker_platform, via_interface)
        known = self._reach.get(key)
        if known is not None:
            return known
        services = self._services.get(receiver)
        if services is None and receiver != self.aid:
            # no service: decided at once, and not remembered (the name comes from the
            # asker, who could make the kept answers take a message's size each)
            return asker_platform == self.platform.name
        allowed = (
            receiver == self.aid
            or asker_platform == self.platform.name
            or (
                services is not None
                and any(
                    visibility_allows(s, asker_platform, via_interface) for s in services.values()
                )
            )
        )
        if len(self._reach) >= _MAX_REACH:
            self._reach.clear()
        self._reach[key] = allowed
        return allowed

    def reachable_now(self, receiver: str, asker_platform: str) -> bool:
        """`reachable` (via the interface) from any thread, as decided before; False: ask that.

        Reads only what `reachable` decided and kept (one lookup each in a set and a
        dict the event loop changes): False when it never decided, or decided no.
        """
        if asker_platform in self._said_left:
            return False
        return self._reach.get((receiver, asker_platform, True)) is True

    def said_left(self, platform: str) -> bool:
        """Whether ``platform`` said, signed, that it left, and was not listed again since."""
        return platform in self._said_left

    def set_left(self, platform: str, left: bool) -> None:
        """Record ``platform``'s signed leave (True), or its signed snapshot since (False).

        The global directory tells: a platform that said it left is not served here (none
        of our agents is `reachable` for it) until it announces itself again.
        """
        if left and platform != self.platform.name:
            self._said_left.add(platform)
        else:
            self._said_left.discard(platform)

    def watch(self, maxlen: int = 1024) -> Subscription[DirectoryEvent]:
        """An async iterator of this DF's changes (all services: local code sees everything)."""
        return _watch(self._watchers, maxlen)

    # -- change propagation -------------------------------------------------------------

    def _tell_watchers(self, op: str, service: ServiceDescription) -> None:
        event = DirectoryEvent(op, self.platform.name, service)
        for inbox in list(self._watchers):
            inbox.put(event)

    async def _changed(
        self, op: str, old: ServiceDescription | None, new: ServiceDescription | None
    ) -> None:
        service = new if new is not None else old
        assert service is not None
        self._tell_watchers(op, service)
        for sub in list(self._subscriptions.subscribers.values()):
            query, platform, via_interface = sub.data

            def visible(s: ServiceDescription) -> bool:
                return query.matches(s) and visibility_allows(s, platform, via_interface)  # noqa: B023

            seen = _seen_as(op, old, new, visible)
            if seen is not None:
                try:
                    await self.reply(
                        sub.message,
                        Performative.INFORM,
                        {"op": seen[0], "service": seen[1].to_obj()},
                    )
                except Exception:
                    log.exception("%s: telling subscriber %s", self, sub.agent)
        wire = _seen_as(op, old, new, _is_public)
        if wire is not None:
            await self._publish_event({"op": wire[0], "service": wire[1].to_obj()})

    async def _publish_event(self, body: dict[str, Any]) -> None:
        p = self.platform
        payload = p.directory_auth.seal(p.name, "df-event", body)
        try:
            await p.transport.publish(p.key("df-events"), payload)
        except TransportError as exc:
            # While the platform closes over a dead transport this is expected.
            level = logging.WARNING if p.running else logging.DEBUG
            log.log(level, "%s: could not publish a directory event: %s", self, exc)

    async def announce_leave(self) -> None:
        """Say, signed, that this platform leaves; then stop answering directory queries.

        Others take a signed leave as the platform gone at once, on any transport; a
        presence that goes without one is checked first where presence can be forged
        (MQTT, ``docs/security.md``), and a DF that no longer answers confirms it.
        """
        self._left = True
        await self._publish_event({"op": "leave"})

    async def _serve_public(self, key: str, payload: bytes) -> bytes | None:
        if self._left:
            return None  # a platform that said it leaves confirms it by its silence
        nonce = b""
        if payload:
            try:
                obj = orjson.loads(payload)
                nonce = base64.b64decode(obj["nonce"], validate=True)
            except (ValueError, TypeError, KeyError, binascii.Error) as exc:
                # a query we cannot answer fresh gets no answer
                self._refuse_query(f"not a directory query: {exc!r}"[:200])
                return None
            if len(nonce) > 64:
                self._refuse_query(f"a nonce of {len(nonce)} bytes (at most 64)")
                return None
        services = [
            s.to_obj()
            for services in self._services.values()
            for s in services.values()
            if _is_public(s)
        ]
        p = self.platform
        return p.directory_auth.seal(p.name, "df", services, nonce=nonce)

    # -- ACL API ------------------------------------------------------------------------

    def drop_subscriptions_of(self, platform: str) -> int:
        """End the subscriptions agents of ``platform`` hold here, telling them nothing (it
        was revoked: nothing is sent to it any more); how many ended."""
        subscribers = self._subscriptions.subscribers
        gone = [key for key in subscribers if platform_of(key[0]) == platform]
        for key in gone:
            del subscribers[key]
        return len(gone)

    def _accept_subscriber(self, message: ACLMessage) -> tuple[ServiceQuery, str, bool]:
        try:
            content = message.content
            query = _query(content if isinstance(content, dict) else None, {})
        except ValidationError as exc:
            raise Refuse(f"invalid query: {exc.errors()[0].get('msg')}") from exc
        if message.content is not None and not isinstance(message.content, dict):
            raise Refuse("the content of a subscribe is a query object")
        asker = platform_of(message.sender)
        if asker != self.platform.name:
            # bounded per platform: each subscription is kept and told of every change
            key = (message.sender, message.conversation_id or "")
            held = sum(
                1
                for k in self._subscriptions.subscribers
                if k != key and platform_of(k[0]) == asker
            )
            if held >= MAX_DF_SUBSCRIPTIONS:
                self.subscriptions_refused += 1
                why = (
                    f"too many directory subscriptions for {asker} "
                    f"(limit {MAX_DF_SUBSCRIPTIONS}: {held} held)"
                )
                # a member may repeat it at its rate limit: a record each within its
                # platform's budget, the rest summed up
                self.platform.audit_refused(message, "df", "subscription-limit", why)
                raise Refuse(f"subscription-limit: {why}")
        return (query, asker, asker != self.platform.name)

    @on_request(FIPA_AGENT_MANAGEMENT)
    async def _on_request(self, message: ACLMessage) -> JsonValue:
        content = message.content
        if not isinstance(content, dict) or not isinstance(content.get("action"), str):
            raise Refuse('the content must be {"action": …}')
        action = content["action"]
        asker = message.sender
        try:
            if action in ("register", "modify"):
                service = ServiceDescription.model_validate(content.get("service"))
                if service.provider != asker:
                    raise Refuse(f"{asker} may only {action} its own services")
                done = await (self.register if action == "register" else self.modify)(service)
                return done.to_obj()
            if action == "deregister":
                name = content.get("name")
                if name is not None and not isinstance(name, str):
                    raise Refuse("name must be a string")
                removed = await self.deregister(asker, name)
                if name is not None and not removed:
                    raise Refuse(f"{asker} has no service {name!r}")
                return len(removed)
            if action == "search":
                query = _query(content.get("query"), {})
                scope = content.get("scope", "local")
                if scope == "global":
                    if self.platform.global_df is None:
                        raise Refuse("this platform keeps no global directory")
                    found = self.platform.global_df.search(query)
                elif scope == "local":
                    platform = platform_of(asker)
                    local = platform == self.platform.name
                    found = self.search(
                        query, asker_platform=None if local else platform, via_interface=not local
                    )
                else:
                    raise Refuse(f"unknown scope {scope!r}")
                return [s.to_obj() for s in found]
        except ValidationError as exc:
            err = exc.errors()[0]
            where = ".".join(str(p) for p in err.get("loc", ()))
            raise Refuse(f"invalid {where or 'value'}: {err.get('msg')}") from exc
        except ServiceError as exc:
            raise Refuse(str(exc)) from exc
        raise Refuse(f"unsupported function {action!r}")


_RESYNC_MAX_WAIT = 30.0  # s between a member's resyncs at most, while it does not answer
UNCONFIRMED_FIRST_WAIT = 1.0
"""Seconds before a platform whose presence holds, but whose first snapshot did not come,
is asked again; the wait doubles after each unanswered query, up to `UNCONFIRMED_MAX_WAIT`."""
UNCONFIRMED_MAX_WAIT = 4.0
"""Seconds between two queries of such a platform at most; each query is also taken from
the name's presence budget (`PRESENCE_RATE` per ``rehandshake_interval``), so a forged
token held under a trusted name costs no more signed queries than toggling it would."""
_STALE_KEYS = 64  # platforms whose stale events are summed up apart, per interval
INVALID_LOG_INTERVAL = 30.0
"""Seconds between two log lines about one signer's invalid directory statements."""
_PRESENCE_QUEUED = 64  # raw presence changes of one platform kept while one is handled
RUNS_REFUSED_KEPT = 32
"""Refused answers `runs_signed` hands its caller at most (the rest are only counted)."""


class GlobalDirectory:
    """The federation's public services as seen from one platform (kept up to date).

    Built from a query of ``dyknow/<fed>/v1/df/*``, then follows ``…/df-events/*`` and the
    presence tokens ``…/alive/*``. Only platforms that are alive count: the entries of a
    platform whose token goes (or that says, signed, that it leaves) are dropped at once
    and watchers get ``platform-gone``.

    With a trust file (the platform's channel has one) only authenticated statements
    count (`DirectoryAuth`): a DF answer must sign this view's fresh nonce, an event must
    be signed and newer than the last; a presence under a name not in the trust file is
    ignored; a platform is ``platform-up`` only once its signed answer came; a signed
    leave of a process whose answer was never read counts only once the platform runs no
    more (`_confirm_leave`; else refused as replayed or late); a presence refused for
    want of that answer is asked again while it holds (``unconfirmed``: after
    `UNCONFIRMED_FIRST_WAIT` s, doubling up to `UNCONFIRMED_MAX_WAIT`, within its
    presence budget) and listed once it answers, its snapshot compared with the entries
    watchers were told of, or taken for gone by the recheck below; where presence can be
    forged (``Transport.forgeable_presence``: MQTT's retained messages), a presence that
    goes without a signed leave is believed only when the platform no longer answers a
    fresh signed query; and every
    ``recheck_interval`` seconds the members, listed or unconfirmed, are asked again (one
    that answers none twice in a row is gone: on zenoh a forged token would otherwise keep a
    dead platform listed, or one that died before its first snapshot came a member). What is
    refused is counted (``refused``) and audited through the channel, within its budget. Each
    platform's presence changes are taken on a task of its own, those that cost a signed
    query within a per-platform budget (`PRESENCE_BURST`, then `PRESENCE_RATE` per the
    channel's ``rehandshake_interval``); the rest are counted (``presence_limited``),
    audited (``df-presence-limited``) and stand for the latest, acted on later.

    With a trust file, events are screened on the transport's thread before any signature
    check (`DfEventGate`, ``event_limit``; None: not screened): a flood of forged ones is
    shed cheaply, counted (``events_shed``) and summed up in ``df-events-shed`` audit
    records, and a member whose events were shed over its budget is asked again at once
    (``resyncs``); so is every member when the subscription's queue overflowed.
    """

    def __init__(
        self,
        platform: "AgentPlatform",
        *,
        query_timeout: float = 1.0,
        recheck_interval: float | None = 30.0,
        event_limit: DfEventLimit | None = DEFAULT_DF_EVENT_LIMIT,
    ) -> None:
        self._platform = platform
        self.query_timeout = query_timeout
        # with a trust file: how often every member is asked again (None: never)
        self._recheck_interval = recheck_interval
        self._recheck_changed = asyncio.Event()  # the recheck task sleeps until due or this
        self._auth: DirectoryAuth = platform.directory_auth
        self._entries: dict[str, dict[tuple[str, str], ServiceDescription]] = {}
        self._alive: set[str] = set()
        # alive, their first snapshot still asked: not exempt from the shared event budget
        self._joining: set[str] = set()
        self._event_counts: dict[str, int] = {}
        # per trusted platform, the boot of the process whose signed answer was read last:
        # a leave of another process (one replayed from before this view read any) is
        # taken only once the platform no longer answers (`_confirm_leave`)
        self._answered_boot: dict[str, int] = {}
        self._leaves_doubted: dict[str, Statement] = {}
        self._watchers: list[Inbox[DirectoryEvent]] = []
        self._presence_watchers: list[Inbox[Presence]] = []
        self._subs: list[Subscription[Message] | Subscription[Presence]] = []
        self.invalid = 0
        self.refused = 0
        self._stale = 0
        self.resyncs = 0  # fresh snapshots taken because events may have been lost, since start
        self.event_gate: DfEventGate | None = None
        self._shed_pending = Pending(1.0 if event_limit is None else event_limit.report_interval)
        # stale events whose signature was checked (normal now and then: one re-sent, or
        # one a snapshot reflected already) are audited summed up, per platform and
        # interval, never one by one; the gate's, unchecked, are in its own summaries
        self._stale_tally = Tally(
            self._audit_stale, interval=self._shed_pending.period, max_keys=_STALE_KEYS
        )
        # invalid statements of trusted signers: logged once per signer per interval
        self._invalid_log = Tally(self._log_invalid, interval=INVALID_LOG_INTERVAL)
        # answers refused to the re-asking of an unconfirmed platform: one asking every few
        # s while a forged token is held, so summed up per name asked (never the name an
        # answer claims: each would be a key of its own) and interval
        self._retry_refused = Tally(self._audit_retry_refused, interval=INVALID_LOG_INTERVAL)
        if self._auth.authenticates and event_limit is not None:
            self.event_gate = DfEventGate(self._auth, event_limit, on_shed=self._shed_pending.add)
        self._resyncing: set[str] = set()
        # a member whose events were shed while its resync ran is asked once more after it;
        # each member is asked at most once per report interval (the interval after a
        # refused or unanswered resync doubles, up to _RESYNC_MAX_WAIT s, while it is alive)
        self._resync_again: set[str] = set()
        self._resync_last: dict[str, float] = {}
        # raw presence changes, per trusted platform, waiting for its own task: one that is
        # slow to answer (or a forged name that never does) holds up no other platform's
        self._presence_queues: dict[str, deque[bool]] = {}
        # per trusted platform, the presence changes that cost a signed query acted on:
        # PRESENCE_BURST at once, then PRESENCE_RATE per the channel's rehandshake_interval
        self._presence_buckets: dict[str, TokenBucket] = {}
        self.presence_limited = 0  # presence changes not acted on one by one (over budget)
        # trusted platforms whose presence holds but whose first signed snapshot did not come
        # (refused): asked again, with backoff, while it holds; the value is the entries
        # watchers were told of (their events came while it was asked), kept to be
        # compared with its snapshot once it answers: what it dropped meanwhile is told
        self._unconfirmed: dict[str, dict[tuple[str, str], ServiceDescription]] = {}
        # when (monotonic) each platform was last taken for gone or left: an answer to a
        # query begun before must not list it again
        self._went_at: dict[str, float] = {}
        # when (monotonic) each trusted platform last answered a fresh signed query, any of
        # them: the recheck counts no silence of one that answered since the last one
        self._answered_at: dict[str, float] = {}
        # per platform followed: set when a raw presence change is queued for its task
        self._presence_changed: dict[str, asyncio.Event] = {}
        self._presence_ignored: dict[str, int] = {}  # counted, not yet in an audit record
        self.version = 0
        """Changes with every change of `services`: a view of them is current while it is equal."""

    async def start(self) -> None:
        """Subscribe, take the snapshot, and follow changes (tasks owned by the platform).

        The snapshot is whole when this returns: every platform whose token is alive (and
        that may count) answered, and so did this one's own directory; or, when the tokens
        could not be asked, every DF answered (zenoh, memory); or the query timed out.
        """
        p = self._platform
        gate = self.event_gate
        self._stale_tally.bind(asyncio.get_running_loop())
        self._retry_refused.bind(asyncio.get_running_loop())
        # Subscribe before the snapshot: what changes meanwhile is queued, not lost. Both
        # at once (over MQTT each waits for the broker); each kept as it comes, for `close`.
        subs: dict[str, Subscription[Any]] = {}

        async def subscribe_events() -> None:
            subs["events"] = sub = await p.transport.subscribe(
                p.key("df-events", "*"), admit=None if gate is None else gate.admit
            )
            self._subs.append(sub)

        async def watch_presence() -> None:
            subs["presence"] = sub = await p.transport.watch_presence(p.key("alive", "*"))
            self._subs.append(sub)

        self._subs = []
        await together(subscribe_events(), watch_presence())
        events: Subscription[Message] = subs["events"]
        presence: Subscription[Presence] = subs["presence"]
        self._subs = [events, presence]  # in this order, whichever the broker took first
        # Those alive are whom to expect: a queryable that never answers (anyone may
        # declare one on dyknow/<fed>/v1/**) keeps even zenoh's query open to its
        # timeout, and MQTT's always is. One alive that answers later, or not in the
        # tokens yet, is taken when its presence comes (the watch above has its history).
        for platform, services in (await self._query("*", expect=self._expected)).items():
            self._set_alive(platform, True)
            self._replace(platform, services)
        if gate is not None:
            p.spawn(self._report_shed(gate), "global-df.shed-report")
        p.spawn(self._follow_events(events), "global-df.events")
        p.spawn(self._follow_presence(presence), "global-df.presence")
        if self._auth.authenticates:
            p.spawn(self._recheck(), "global-df.recheck")

    def close(self) -> None:
        """Stop following; watchers' iterators end."""
        for sub in self._subs:
            try:
                sub.close()
            except TransportError:
                pass
        for inbox in self._watchers:
            inbox.close()
        for pinbox in self._presence_watchers:
            pinbox.close()
        self._watchers.clear()
        self._presence_watchers.clear()
        # what was counted since the last summary is reported, not lost with the platform
        self._stale_tally.close()
        self._invalid_log.close()
        self._retry_refused.close()
        for platform in list(self._presence_ignored):
            self._presence_limit(platform, 0, audit=True)
        gate = self.event_gate
        if gate is not None:
            details, summary, _ = gate.take_report(time.monotonic(), final=True)
            for claimed, reason in details:
                self._audit_refusal(claimed, f"directory event shed: {reason}", "df-events")
            if summary is not None:
                self._audit_shed(gate.limit, summary)

    @property
    def recheck_interval(self) -> float | None:
        """Seconds between asking every member again (None: never); may be changed live."""
        return self._recheck_interval

    @recheck_interval.setter
    def recheck_interval(self, interval: float | None) -> None:
        self._recheck_interval = interval
        self._recheck_changed.set()  # the sleeping recheck task counts from the new interval

    @property
    def platforms(self) -> list[str]:
        """The platforms known alive: listed, or their first snapshot asked now (not yet up).

        One whose presence just came is in it while its first snapshot is asked (three
        queries at most); an unconfirmed one only once its signed answer came.
        """
        return sorted(p for p in self._alive if p not in self._unconfirmed)

    @property
    def listed(self) -> list[str]:
        """The platforms listed: alive, and their signed directory snapshot answered.

        Who may receive a stream goes by this, never by `platforms`: a presence token
        is not authentication, and one whose first snapshot is still asked may be a
        forged token under a trusted name whose platform is not running.
        """
        return sorted(
            p for p in self._alive if p not in self._joining and p not in self._unconfirmed
        )

    def services(self, platform: str | None = None) -> list[ServiceDescription]:
        """Every public service known (of ``platform`` only, when given)."""
        # an unconfirmed platform's entries, restored while it is asked again, count only
        # once it answered: a forged presence must not make a provider now and then
        if platform is not None:
            if platform in self._unconfirmed:
                return []
            return list(self._entries.get(platform, {}).values())
        unconfirmed = self._unconfirmed
        return [
            s
            for name, entries in self._entries.items()
            if name not in unconfirmed
            for s in entries.values()
        ]

    def search(
        self, query: ServiceQuery | dict[str, Any] | None = None, **fields: Any
    ) -> list[ServiceDescription]:
        """The public services of the federation matching ``query`` (or keyword fields)."""
        q = _query(query, fields)
        return [s for s in self.services() if q.matches(s)]

    def watch(self, maxlen: int = 1024) -> Subscription[DirectoryEvent]:
        """An async iterator of changes: services, and platforms coming and going."""
        return _watch(self._watchers, maxlen)

    def watch_presence(self, maxlen: int = 1024) -> Subscription[Presence]:
        """Platforms coming (``alive``) and going, as this view believes them: authenticated.

        The keys are the presence keys (``dyknow/<fed>/v1/alive/<platform>``), so a
        consumer of a transport's ``watch_presence`` can take this one instead.
        """
        inbox: Inbox[Presence] = Inbox(asyncio.get_running_loop(), maxlen)
        self._presence_watchers.append(inbox)

        def remove() -> None:
            if inbox in self._presence_watchers:
                self._presence_watchers.remove(inbox)

        return Subscription(inbox, remove)

    def _set_alive(self, platform: str, alive: bool, *, joining: bool = False) -> None:
        """Take ``platform`` for alive or not; the event gate's exemption follows at once.

        ``joining``: its presence was taken and its first signed snapshot is asked. It is
        exempt from the shared budget only once that answer came: anyone may make a
        trusted name's presence appear, and a silent name would keep its exemption for
        as long as the query lasts. Its events shed over the shared budget meanwhile
        have it asked again (`DfEventGate.joining`): no change it sends is lost.
        """
        if alive:
            self._alive.add(platform)
        else:
            self._alive.discard(platform)
        if alive and joining:
            self._joining.add(platform)
        else:
            self._joining.discard(platform)
        gate = self.event_gate
        if gate is not None:
            # replaced whole: the transport's thread reads them without a lock; priority
            # first, so that a name leaving joining for it is never in neither set meanwhile
            gate.priority = frozenset(self._alive - self._joining)
            gate.joining = frozenset(self._joining)

    def _tell(self, event: DirectoryEvent) -> None:
        for inbox in list(self._watchers):
            inbox.put(event)
        if event.op in ("platform-up", "platform-gone"):
            change = Presence(
                self._platform.key("alive", event.platform), event.op == "platform-up"
            )
            for pinbox in list(self._presence_watchers):
                pinbox.put(change)

    def _audit_stale(
        self, platform: object, count: int, detail: str, seconds: float | None
    ) -> None:
        """One audit record for ``count`` stale events of ``platform`` (summed up)."""
        self._platform.audit(
            verdict="dropped",
            stage="df-events-stale",
            code="stale",
            count=count,
            **{"from": platform},
            reason=(
                f"stale: {count} directory event(s) of {platform!r} not newer than its last "
                f"accepted one dropped{since(seconds)} (last: {detail[:200]})"
            ),
        )

    def _audit_retry_refused(
        self, asked: object, count: int, detail: str, seconds: float | None
    ) -> None:
        """One audit record for ``count`` refused answers to the re-asking of ``asked``.

        Keyed on the name asked (trusted), whatever name each answer claims: the last
        claimed one, cut short, is in the detail.
        """
        self._platform.audit(
            verdict="dropped",
            stage="df",
            count=count,
            **{"from": asked},
            reason=(
                f"directory answer: {count} answer(s) to the asking of {asked!r}, asked again "
                f"while its presence holds unconfirmed, refused{since(seconds)} (last: "
                f"{detail[:200]})"
            ),
        )

    def _log_invalid(
        self, platform: object, count: int, detail: str, seconds: float | None
    ) -> None:
        """One warning for ``count`` invalid statements signed by ``platform`` (summed up)."""
        if count == 1:
            log.warning("global-df[%s]: %s", self._platform.name, detail[:300])
            return
        log.warning(
            "global-df[%s]: %d invalid directory statements from %r%s (last: %s)",
            self._platform.name,
            count,
            platform,
            since(seconds),
            detail[:300],
        )

    def _audit_invalid(self, platform: str, reason: str, stage: str) -> None:
        """Audit a signed statement whose body is no directory's, within the channel's budget."""
        # signed, yet as cheap to repeat as unsigned input: the same budget bounds the records
        audit = getattr(self._platform.channel, "audit_unauthenticated", None)
        if audit is not None:
            audit(platform, f"invalid: {reason}"[:300], stage)

    def _refuse(self, claimed: str | None, reason: str, stage: str) -> None:
        """Count and audit what did not authenticate (the channel bounds the records)."""
        self.refused += 1
        self._audit_refusal(claimed, reason, stage)

    def _audit_refusal(self, claimed: str | None, reason: str, stage: str) -> None:
        """Log and audit a refusal through the channel (which bounds the records)."""
        log.info(
            "global-df[%s]: %s from %r refused: %s", self._platform.name, stage, claimed, reason
        )
        audit = getattr(self._platform.channel, "audit_unauthenticated", None)
        if audit is not None:
            audit(claimed, reason, stage)

    async def _expected(self) -> set[str] | None:
        """The platforms whose answers make a snapshot whole: those alive that may count.

        This one's own name is always there (its token is declared after the snapshot);
        None when the tokens could not be asked.
        """
        p = self._platform

        def trusted(key: str) -> bool:
            return self._auth.trusted(key.rpartition("/")[2])

        try:
            # screened as they come: invented presences cannot crowd trusted ones out
            alive = await p.transport.tokens(
                p.key("alive", "*"), timeout=self.query_timeout, keep=trusted
            )
        except TransportError as exc:
            log.warning("global-df[%s]: asking the tokens failed: %s", p.name, exc)
            return None
        return {key.rpartition("/")[2] for key in alive} | {p.name}

    async def _query(
        self,
        platform: str,
        timeout: float | None = None,
        *,
        expect: set[str] | Callable[[], Awaitable[set[str] | None]] | None = None,
        summed: bool = False,
    ) -> dict[str, list[ServiceDescription]]:
        """Ask the DF(s) for their public services: {platform: services} of those that answered.

        The query ends once every platform of ``expect`` answered (one named: that one),
        or when the transport knows all did, or at the timeout. ``expect`` may be a
        function finding that set, called once the query is sent (its replies queue
        meanwhile); only an authenticated answer counts. ``summed``: answers refused are
        audited summed up per name asked (`_retry_refused`), not one by one.
        """
        if expect is None and "*" not in platform:
            expect = {platform}  # its answer is all there is (MQTT's query would wait on)
        nonce = make_nonce()
        found: dict[str, list[ServiceDescription]] = {}
        try:
            async with await self._platform.transport.ask(
                self._platform.key("df", platform),
                orjson.dumps({"v": WIRE_VERSION, "nonce": base64.b64encode(nonce).decode()}),
                timeout=self.query_timeout if timeout is None else timeout,
            ) as replies:
                wanted = await expect() if callable(expect) else expect
                async for reply in replies:
                    self._take(reply, nonce, found, summed)
                    if wanted is not None and wanted.issubset(found):
                        break
        except TransportError as exc:
            log.warning("global-df[%s]: query failed: %s", self._platform.name, exc)
        return found

    def _take(
        self,
        reply: Reply,
        nonce: bytes,
        found: dict[str, list[ServiceDescription]],
        summed: bool = False,
    ) -> None:
        """Add a directory answer to ``found`` if it authenticates; refuse and count it if not."""
        if not reply.ok:
            return
        name = reply.key.rpartition("/")[2]
        where = None if "*" in name else name
        try:
            statement = self._auth.open(reply.payload, "df", platform=where, nonce=nonce)
        except DirectoryStatementError as exc:
            if summed:
                self.refused += 1
                # keyed on the name asked, not the answer's claimed ``from``: an invented
                # name per answer would be a record of its own each, past the budget
                claimed = exc.platform if exc.platform is not None else where
                self._retry_refused.add(
                    where, f"claiming {str(claimed)[:64]!r}: {exc.reason[:200]}"
                )
            else:
                self._refuse(exc.platform or where, f"directory answer: {exc.reason}", "df")
            return
        try:
            items = statement.body
            if not isinstance(items, list):
                raise ValueError("not a list")
            services = [ServiceDescription.model_validate(i) for i in items]
        except (ValueError, ValidationError) as exc:
            self.invalid += 1
            self._invalid_log.add(statement.platform, f"bad answer from {reply.key}: {exc}")
            self._audit_invalid(statement.platform, f"directory answer: {exc}", "df")
            return
        name = statement.platform
        if not self._auth.trusted(name):
            self._refuse(name, "directory answer from a platform not in the trust file", "df")
            return
        found[name] = [s for s in services if s.platform == name]
        self._answered_boot[name] = statement.boot
        self._answered_at[name] = time.monotonic()

    def _replace(self, platform: str, services: Iterable[ServiceDescription]) -> None:
        old = self._entries.get(platform, {})
        new = {s.key: s for s in services}
        self._entries[platform] = new
        self.version += 1
        for key, service in new.items():
            before = old.get(key)
            if before is None:
                self._tell(DirectoryEvent("register", platform, service))
            elif before != service:
                self._tell(DirectoryEvent("modify", platform, service))
        for key, service in old.items():
            if key not in new:
                self._tell(DirectoryEvent("deregister", platform, service))

    def _apply(self, platform: str, op: str, service: ServiceDescription) -> None:
        entries = self._entries.setdefault(platform, {})
        before = entries.get(service.key)
        if op == "deregister":
            if before is not None:
                del entries[service.key]
                self.version += 1
                self._tell(DirectoryEvent("deregister", platform, before))
            return
        entries[service.key] = service
        self.version += 1
        if before is None:
            self._tell(DirectoryEvent("register", platform, service))
        elif before != service:
            self._tell(DirectoryEvent("modify", platform, service))

    @property
    def stale(self) -> int:
        """Events not newer than the last accepted of their platform (dropped), since start."""
        gate = self.event_gate
        return self._stale + (0 if gate is None else gate.stale)

    @property
    def events_shed(self) -> int:
        """Directory events dropped before their signature check, since start."""
        return 0 if self.event_gate is None else self.event_gate.shed_total

    async def _report_shed(self, gate: DfEventGate) -> None:
        """Audit the events shed, summed up once per interval; ask again whom they hid."""
        while True:
            await self._shed_pending.take()  # asleep while nothing is shed
            while True:
                details, summary, resync = gate.take_report(time.monotonic())
                for claimed, reason in details:
                    self._audit_refusal(claimed, f"directory event shed: {reason}", "df-events")
                if summary is not None:
                    self._audit_shed(gate.limit, summary)
                self._want_resync(resync)
                if summary is not None or not gate.pending:
                    break
                # a summary is due within the interval: the flood may be over by then
                await asyncio.sleep(gate.limit.report_interval / 4)

    def _audit_shed(self, limit: DfEventLimit, summary: dict[str, Any]) -> None:
        self._platform.audit(
            verdict="dropped",
            stage="df-events-shed",
            count=summary["count"],
            by_reason=summary["by_reason"],
            reason=(
                f"directory events shed: {summary['count']} dropped before any signature "
                f"check{shed_counts(summary)}; budget {limit.per_platform:g}/s per platform, "
                f"burst {limit.per_platform_burst:g}; {limit.total:g}/s for platforms not "
                f"in the directory, burst {limit.total_burst:g})"
            ),
        )

    def _want_resync(self, platforms: Iterable[str]) -> None:
        """Take a fresh snapshot of each of ``platforms`` alive: events of theirs may be lost."""
        for platform in platforms:
            if platform not in self._alive:
                continue
            if platform in self._resyncing:
                self._resync_again.add(platform)  # shed after its answer, maybe: once more
                continue
            self._resyncing.add(platform)
            self._platform.spawn(self._resync(platform), f"global-df.resync[{platform}]")

    async def _resync(self, platform: str) -> None:
        """Ask ``platform`` for its snapshot until it answered one taken after the last shed.

        At most once per report interval; while it is alive and its answer does not come
        (its directory shedding a flood of queries, say), again after a wait that doubles.
        """
        gate = self.event_gate
        interval = gate.limit.report_interval if gate is not None else 1.0
        backoff = interval
        try:
            while platform in self._alive:
                wait = self._resync_last.get(platform, -math.inf) + interval - time.monotonic()
                if wait > 0:
                    await asyncio.sleep(wait)
                self._resync_last[platform] = time.monotonic()
                self._resync_again.discard(platform)
                self.resyncs += 1
                answered = await self._fetch(platform)
                if answered and platform not in self._resync_again:
                    return
                if not answered:
                    await asyncio.sleep(backoff)
                    backoff = min(backoff * 2, _RESYNC_MAX_WAIT)
        finally:
            self._resyncing.discard(platform)
            self._resync_again.discard(platform)

    async def _follow_events(self, sub: Subscription[Message]) -> None:
        lost = 0
        async for item in sub:
            if sub.dropped != lost:
                # the queue overflowed: an authenticated event may be among those lost
                lost = sub.dropped
                self._want_resync(list(self._alive))
            platform = item.key.rpartition("/")[2]
            try:
                statement = self._auth.open(item.payload, "df-event", platform=platform)
            except DirectoryStatementError as exc:
                if exc.reason.startswith("stale"):
                    self._stale += 1  # already reflected, or replayed: changes nothing
                    self._stale_tally.add(platform, exc.reason)
                    continue
                if self._auth.authenticates:
                    self._refuse(platform, f"directory event: {exc.reason}", "df-events")
                else:
                    self.invalid += 1
                    self._invalid_log.add(platform, f"bad event on {item.key}: {exc}")
                continue
            self._event_counts[platform] = self._event_counts.get(platform, 0) + 1
            obj = statement.body
            if isinstance(obj, dict) and obj.get("op") == "leave":
                self._take_leave(platform, statement)
                continue
            if platform not in self._alive:
                continue  # its snapshot will be taken when its token appears
            try:
                if not isinstance(obj, dict):
                    raise ValueError("the body of a directory event is an object")
                op = obj.get("op")
                if op not in _OPS:
                    raise ValueError(f"unknown op {op!r}")
                service = ServiceDescription.model_validate(obj.get("service"))
                if service.platform != platform:
                    raise ValueError(f"{platform} spoke for {service.provider}")
            except (ValueError, ValidationError) as exc:
                self.invalid += 1
                self._invalid_log.add(platform, f"bad event on {item.key}: {exc}")
                self._audit_invalid(platform, f"directory event: {exc}", "df-events")
                continue
            self._apply(platform, op, service)
        self._platform.ended(
            sub,
            f"directory events subscription {self._platform.key('df-events', '*')}",
            "other platforms' directory changes (services added, removed, a signed leave) "
            "are no longer followed: this platform's directory of their services goes stale",
        )

    def _take_leave(self, platform: str, statement: Statement) -> None:
        """Take ``platform``'s signed leave: at once when it is the leave of the process read.

        A leave of a process whose signed answer this view never read (its first snapshot
        under way, or not asked yet) may be one anyone recorded and replays within the
        skew, or an earlier process's, late: it is taken only once the platform runs no
        more, and refused (counted, audited) while it does (`_confirm_leave`).
        """
        if not self._auth.authenticates or self._answered_boot.get(platform) == statement.boot:
            # whether or not still listed (its presence may have gone first): signed
            self._gone(platform)
            self._left(platform, statement.ts_ms / 1000)
            return
        doubted = platform in self._leaves_doubted
        self._leaves_doubted[platform] = statement  # the latest stands for those before
        if doubted:
            return
        try:
            self._platform.spawn(self._confirm_leave(platform), f"global-df.leave[{platform}]")
        except AgentError:
            self._leaves_doubted.pop(platform, None)  # the platform is closing

    async def _confirm_leave(self, platform: str) -> None:
        """Take the doubted leave of ``platform`` once it no longer runs; refuse it while it does.

        It runs while it answers a fresh signed query, while an answer of another process
        of its is read meanwhile (a snapshot under way), or while it talks to this
        platform (authenticated envelopes: its queryable may be shedding anyone's flood of
        queries). Only three checks in a row finding none of these take the leave.
        """
        before = self._answered_boot.get(platform)
        running: str | None = None
        # heard from since the check began, pauses between queries included: a shed query
        # ends at once, and a member's traffic comes when it comes
        began = time.monotonic()
        try:
            for attempt in range(3):
                if await self._answers(platform):
                    running = "answers"
                    break
                boot = self._answered_boot.get(platform)
                if boot != before and boot != self._leaves_doubted[platform].boot:
                    running = "answered meanwhile"
                    break
                if self._heard_lately(platform, time.monotonic() - began):
                    running = "talks to this platform"
                    break
                if attempt < 2:
                    # a shed query ends at once: the next may find its budget again
                    await asyncio.sleep(self.query_timeout)
        finally:
            statement = self._leaves_doubted.pop(platform)
        at = statement.ts_ms / 1000
        if running is not None and self._answered_boot.get(platform) != statement.boot:
            self._refuse(
                platform,
                f"directory event: a signed leave of its process of boot {statement.boot}, "
                f"whose directory this view never read, while it {running} (last boot read: "
                f"{self._answered_boot.get(platform)}): replayed or late",
                "df-events",
            )
            # sessions agreed before that leave are its earlier process's (a late leave
            # after a restart): retired; what its running process agreed since stays
            left = getattr(self._platform.channel, "peer_left", None)
            if left is not None:
                left(platform, at)
            return
        self._gone(platform)
        self._left(platform, at)

    def _left(self, platform: str, at: float) -> None:
        """Tell the channel that ``platform`` left at ``at`` (POSIX s), as it signed.

        Only a signed leave says so (a presence cleared may be forged): the channel then
        seals for it on none of its sessions agreed before ``at`` again, and ends a key
        exchange with it begun before (a leave replayed, or late after a restart, must
        not end what the platform's next process agreed).
        """
        if not self._auth.authenticates:
            return
        df = self._platform.df
        if df is not None:
            df.set_left(platform, True)  # not served until its signed snapshot lists it again
        left = getattr(self._platform.channel, "peer_left", None)
        if left is not None:
            left(platform, at)

    def _up(self, platform: str) -> None:
        """``platform`` is listed (again), on its signed answer: served, and watchers told."""
        df = self._platform.df
        if df is not None:
            df.set_left(platform, False)
        self._tell(DirectoryEvent("platform-up", platform, None))

    def _drop_entries(self, platform: str) -> bool:
        """Drop ``platform``'s entries; whether it had any."""
        had = bool(self._entries.pop(platform, None))
        self.version += 1
        return had

    def revoked(self, platform: str) -> None:
        """``platform`` was removed from the trust store: out of this view now, as when its
        presence went (its entries dropped, watchers told ``platform-gone``); its token,
        snapshots and events are refused from then on (its key is not trusted)."""
        self._gone(platform)

    def _gone(self, platform: str) -> None:
        self._went_at[platform] = time.monotonic()
        held = self._unconfirmed.pop(platform, None)
        told = bool(held)
        if platform in self._alive:
            self._set_alive(platform, False)
            had = self._drop_entries(platform)
            # one asked again (unconfirmed) is alive only while asked: told gone only if
            # watchers were told of entries of its, else of a name never up (a token
            # anyone holds under a trusted name)
            if held is None or told or had:
                self._tell(DirectoryEvent("platform-gone", platform, None))
        elif told:
            # watchers saw entries of its (signed) events before its snapshot was refused
            self._tell(DirectoryEvent("platform-gone", platform, None))

    @property
    def unconfirmed(self) -> list[str]:
        """Trusted platforms whose presence holds but whose signed snapshot has not come yet."""
        return sorted(self._unconfirmed)

    async def _follow_presence(self, sub: Subscription[Presence]) -> None:
        """Hand each raw presence change of a trusted platform to that platform's own task."""
        async for change in sub:
            platform = change.key.rpartition("/")[2]
            if not self._auth.trusted(platform):
                self._refuse(platform, "presence of a platform not in the trust file", "presence")
                continue
            queue = self._presence_queues.get(platform)
            if queue is None:
                queue = self._presence_queues[platform] = deque()
                try:
                    self._platform.spawn(
                        self._follow_platform(platform, queue), f"global-df.presence[{platform}]"
                    )
                except AgentError:
                    return  # the platform is closing: nothing to follow for
            if len(queue) >= _PRESENCE_QUEUED:
                # a toggling faster than the changes are handled: only the latest can matter
                self._presence_limit(platform, len(queue))
                queue.clear()
            queue.append(change.alive)
            changed = self._presence_changed.get(platform)
            if changed is not None:
                changed.set()  # its task may be waiting to ask an unconfirmed platform again
        self._platform.ended(
            sub,
            f"directory presence watch {self._platform.key('alive', '*')}",
            "other platforms coming and going are no longer seen but by their signed leaves "
            "and the directory's rechecks (where they run): till then one that goes without "
            "its signed leave (a crash) stays in this platform's directory, one that comes is "
            "not added to it",
        )

    async def _follow_platform(self, platform: str, queue: deque[bool]) -> None:
        """Act on ``platform``'s presence changes in order, those that cost a query within budget.

        Presence is not authenticated, and taking one that appears (or, where presence can
        be forged, one that goes) costs a signed query: per platform, `PRESENCE_BURST` of
        those at once, then `PRESENCE_RATE` per the channel's ``rehandshake_interval``. A
        change over the budget, and those that come until the budget allows, are counted
        (``presence_limited``), audited in one record, and stand for the latest of them,
        acted on then.
        """
        changed = self._presence_changed[platform] = asyncio.Event()
        wait = UNCONFIRMED_FIRST_WAIT
        try:
            while True:
                while queue:
                    alive = queue.popleft()
                    if self._presence_costs(platform, alive):
                        bucket = self._presence_bucket(platform)
                        if not bucket.take(time.monotonic()):
                            alive = await self._presence_over_budget(platform, alive, queue, bucket)
                    await self._on_presence(platform, alive)
                    wait = UNCONFIRMED_FIRST_WAIT
                if platform not in self._unconfirmed:
                    return
                # Its presence holds, its snapshot did not come (a loaded machine, its
                # directory shedding queries): asked again soon, not only at the recheck;
                # each asking is taken from its presence budget, so a forged token held
                # under its name costs no more signed queries than toggling it would
                if not await self._await_retry(platform, queue, changed, wait):
                    continue
                await self._confirm(platform, timeout=max(self.query_timeout, wait))
                wait = min(wait * 2, UNCONFIRMED_MAX_WAIT)
        finally:
            if self._presence_queues.get(platform) is queue:
                del self._presence_queues[platform]
            if self._presence_changed.get(platform) is changed:
                del self._presence_changed[platform]

    async def _await_retry(
        self, platform: str, queue: deque[bool], changed: asyncio.Event, wait: float
    ) -> bool:
        """Wait ``wait`` s, then for ``platform``'s presence budget; whether to ask it now.

        False when a presence change came meanwhile (acted on first), or it is no longer
        unconfirmed.
        """
        bucket = self._presence_bucket(platform)
        while True:
            changed.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(wait):
                    await changed.wait()
            if queue or platform not in self._unconfirmed:
                return False
            if bucket.take(time.monotonic()):
                return True
            wait = max((1.0 - bucket.tokens) / bucket.rate, 0.05)

    def _presence_costs(self, platform: str, alive: bool) -> bool:
        """Whether acting on this presence change of ``platform`` asks it a signed query."""
        if alive:
            return platform not in self._alive
        forgeable = getattr(self._platform.transport, "forgeable_presence", False)
        return forgeable and self._auth.authenticates and platform in self._alive

    def _presence_bucket(self, platform: str) -> TokenBucket:
        """``platform``'s budget of presence changes acted on (one per trusted name)."""
        bucket = self._presence_buckets.get(platform)
        if bucket is None:
            interval = getattr(self._platform.channel, "rehandshake_interval", 5.0)
            bucket = presence_bucket(interval, time.monotonic())
            self._presence_buckets[platform] = bucket
        return bucket

    async def _presence_over_budget(
        self, platform: str, alive: bool, queue: deque[bool], bucket: TokenBucket
    ) -> bool:
        """Wait for ``platform``'s budget; the latest change by then (counted and audited)."""
        ignored = 1
        while not bucket.take(time.monotonic()):
            await asyncio.sleep(max((1.0 - bucket.tokens) / bucket.rate, 0.05))
            if queue:
                ignored += len(queue)
                alive = queue[-1]
                queue.clear()
        self._presence_limit(platform, ignored, alive, audit=True)
        return alive

    def _presence_limit(
        self, platform: str, n: int, alive: bool | None = None, *, audit: bool = False
    ) -> None:
        """Count ``n`` presence changes of ``platform`` not acted on; audit what was summed.

        ``alive``: the change acted on instead (None: none, the view closes).
        """
        self.presence_limited += n
        total = self._presence_ignored.pop(platform, 0) + n
        if not audit:
            self._presence_ignored[platform] = total
            return
        if not total:
            return
        interval = getattr(self._platform.channel, "rehandshake_interval", 5.0)
        then = (
            "the view closed before acting on the latest"
            if alive is None
            else f"acted on the latest ({'alive' if alive else 'gone'}) instead"
        )
        self._platform.audit(
            verdict="dropped",
            stage="df-presence-limited",
            count=total,
            reason=(
                f"presence changes of {platform!r} not acted on one by one: {total} over "
                f"the budget of {PRESENCE_BURST} at once and {PRESENCE_RATE:g} per "
                f"{interval:g} s (presence is not authenticated; each costs a signed "
                f"query); {then}"
            ),
            **{"from": platform},
        )

    async def _on_presence(self, platform: str, alive: bool) -> None:
        """Act on one raw presence change of trusted ``platform``."""
        forgeable = getattr(self._platform.transport, "forgeable_presence", False)
        if alive:
            if platform in self._alive:
                return
            self._restore(platform)
            self._set_alive(platform, True, joining=True)
            try:
                confirmed = await self._fetch(platform)
            except Exception:
                # not a transport's error (those are an unanswered query): whatever it is,
                # the name must not stay alive, nor exempt, for good
                log.exception("global-df[%s]: taking %r's snapshot", self._platform.name, platform)
                if platform in self._alive:
                    self._set_alive(platform, False)
                    self._drop_entries(platform)
                return
            if platform not in self._alive or platform not in self._joining:
                return  # gone, or listed by the recheck, meanwhile
            if not confirmed and self._auth.authenticates:
                # a token anyone could declare; the platform itself did not answer (yet):
                # refused once, then asked again while the token holds
                self._hold(platform)
                self._refuse(platform, "presence without a signed directory answer", "presence")
                return
            self._listed(platform)
        elif platform in self._unconfirmed:
            self._gone(platform)  # never confirmed: nothing to check, nothing to stop
        elif platform in self._alive:
            if forgeable and self._auth.authenticates and await self._answers(platform):
                self._refuse(
                    platform,
                    "presence cleared without a signed leave while the platform "
                    "still answers: ignored",
                    "presence",
                )
                return
            self._gone(platform)

    def _restore(self, platform: str) -> None:
        """Put back the entries watchers were told of for unconfirmed ``platform``.

        Its events while it is asked, and its snapshot, are compared with what watchers
        believe: a service it deregistered meanwhile is told ``deregister``.
        """
        told = self._unconfirmed.get(platform)
        if told:
            self._entries[platform] = dict(told)
            self.version += 1

    def _hold(self, platform: str) -> None:
        """Take ``platform`` for not alive, unconfirmed: its entries kept aside, not served."""
        self._set_alive(platform, False)
        self._unconfirmed[platform] = self._entries.pop(platform, {})
        self.version += 1

    async def _confirm(self, platform: str, timeout: float) -> None:
        """Ask unconfirmed ``platform`` again (one query): listed if it answers, signed."""
        self._restore(platform)
        self._set_alive(platform, True, joining=True)
        try:
            confirmed = await self._fetch(platform, unanswered=1, timeout=timeout, summed=True)
        except Exception:
            log.exception("global-df[%s]: asking %r again", self._platform.name, platform)
            confirmed = False
        if platform not in self._alive or platform not in self._unconfirmed:
            return  # gone, or listed by the recheck, meanwhile
        if not confirmed:
            self._hold(platform)
            return
        log.info("global-df[%s]: %r answered at last: listed", self._platform.name, platform)
        self._listed(platform)

    def _listed(self, platform: str) -> None:
        """``platform`` answered, signed: listed, its services counted, watchers told."""
        if self._unconfirmed.pop(platform, None) is not None:
            self.version += 1  # its services count from now on
        self._set_alive(platform, True)  # answered: exempt from the shared budget now
        self._up(platform)

    async def _recheck_sleep(self, wait: float | None) -> None:
        """Sleep ``wait`` s (None: for ever), or until the recheck interval is changed."""
        self._recheck_changed.clear()
        try:
            async with asyncio.timeout(wait):
                await self._recheck_changed.wait()
        except TimeoutError:
            pass

    async def _recheck(self) -> None:
        """Ask every member again now and then: the liveness presence alone cannot prove.

        On zenoh a token stays while *any* session holds one on the key, so a token forged
        under a running platform's name would keep it listed after it dies. A member that
        answers no signed query twice in a row is gone; so is one held unconfirmed (it died
        while its first snapshot was asked, a token held under its name: else asked again,
        and a member, for as long as the token holds). A signed answer to any query since
        the previous recheck took its answers counts as an answer. One that answers while
        not listed (it was taken for gone while it hung, or is unconfirmed) is up again.
        """
        misses: dict[str, int] = {}
        last = time.monotonic()
        checked = -math.inf  # when the last recheck took its answers (none yet)
        while True:
            # Sleep until the next recheck is due, or until the interval is changed: an idle
            # member has nothing to wake for in between.
            interval = self._recheck_interval
            if interval is None:
                await self._recheck_sleep(None)
                continue
            wait = last + interval - time.monotonic()
            if wait > 0:
                await self._recheck_sleep(wait)
                continue
            last = began = time.monotonic()
            # generous: a busy member must not be taken for gone (nothing waits on this)
            answered = await self._query("*", max(self.query_timeout, 5.0))
            # a signed answer to any other fresh query since the last recheck took its
            # answers (its re-asking, a resync) proves it runs as well: a slow member listed
            # on its re-asking's answer is not taken for gone on this recheck's silence.
            # Each counts for one recheck: a dead member's last one keeps it an interval at most
            after, checked = checked, time.monotonic()
            for went in [p for p in misses if p not in self._alive and p not in self._unconfirmed]:
                del misses[went]  # a silence before it went counts not against its return
            for platform in sorted(self._alive | self._unconfirmed.keys()):
                if platform in self._joining and platform not in self._unconfirmed:
                    continue  # its first snapshot is asked by its own task meanwhile (bounded)
                if (
                    platform == self._platform.name
                    or platform in answered
                    or self._answered_at.get(platform, -math.inf) > after
                    or self._heard_lately(platform, 2 * interval)
                ):
                    misses.pop(platform, None)
                    continue
                misses[platform] = misses.get(platform, 0) + 1
                if misses[platform] >= 2:
                    del misses[platform]
                    never = " (never listed: its snapshot never came)"
                    self._refuse(
                        platform,
                        "presence still held, but the platform answered no signed directory "
                        "query twice in a row: taken for gone"
                        + (never if platform in self._unconfirmed else ""),
                        "presence",
                    )
                    self._gone(platform)
            for platform, services in answered.items():
                if platform == self._platform.name:
                    continue
                if self._went_at.get(platform, -math.inf) >= began:
                    # it left (signed) or was taken for gone after it answered: the answer
                    # is older than that, and must not serve it again
                    continue
                # not listed, or its snapshot asked meanwhile: this answer is as signed
                if platform not in self._alive or platform in self._joining:
                    if platform not in self._alive:
                        self._restore(platform)
                    self._unconfirmed.pop(platform, None)
                    self._set_alive(platform, True)
                    self._replace(platform, services)
                    self._up(platform)

    def _heard_lately(self, platform: str, within: float) -> bool:
        """Whether an authenticated envelope of ``platform`` opened here within ``within`` s.

        Authenticated traffic proves the platform runs as well as a signed answer does, and
        its directory queryable may be shedding a flood of anyone's queries meanwhile: a
        member that talks to this platform is never taken for gone for that.
        """
        sessions = getattr(self._platform.channel, "sessions", None)
        heard = getattr(sessions, "heard_since", None)
        if heard is None:
            return False
        since = heard(platform)
        return since is not None and since <= within

    async def _answers(self, platform: str) -> bool:
        """Whether ``platform`` answers a fresh signed query now."""
        return platform in await self._query(platform)

    async def _fetch(
        self,
        platform: str,
        *,
        unanswered: int = 3,
        timeout: float | None = None,
        summed: bool = False,
    ) -> bool:
        """Take ``platform``'s snapshot; again if events came meanwhile (they may be newer).

        True when the platform answered (authenticated, with a trust file). With a trust
        file, up to ``unanswered`` queries go unanswered before giving up.
        """
        misses = 0
        for attempt in range(3):
            seen = self._event_counts.get(platform, 0)
            services = (await self._query(platform, timeout, summed=summed)).get(platform)
            if platform not in self._alive:
                return False  # gone while we asked
            if services is None:
                misses += 1
                if self._auth.authenticates and misses < unanswered:
                    continue  # it may still be starting: ask again before refusing
                return False  # no answer: keep what the events say (without a trust file)
            df = self._platform.df
            if df is not None and self._auth.authenticates:
                # signed, to our fresh nonce: a platform that said it left is served again
                # now, not after the events that came meanwhile are taken too (a restarted
                # one asks at once)
                df.set_left(platform, False)
            if self._event_counts.get(platform, 0) == seen or attempt == 2:
                self._replace(platform, services)
                return True
        return False


# -- client helpers (ACL) ----------------------------------------------------------------


async def runs_signed(
    transport: Transport,
    keys: "KeyPair",
    trust: "TrustStore",
    platform: str,
    *,
    timeout: float = 2.0,
    tries: int = 3,
    refused: list[tuple[str | None, str]] | None = None,
) -> bool:
    """Whether ``platform`` answers a fresh directory query with a statement it signed.

    What proves a platform runs, where its presence (a liveliness token, a retained MQTT
    message) is only a hint anyone on the network can give: the answer must verify with
    the key ``trust`` holds for ``platform`` (``keys``: this side's, for its own name).
    Answers that do not are refused: the first `RUNS_REFUSED_KEPT` appended to
    ``refused`` (the platform it claims, why) when given, and all of them counted and
    logged in one warning at the end (this runs before the platform and its audit exist;
    anyone may answer, as often as they like).
    """
    auth = DirectoryAuth(trust.federation, keys, trust)
    key = f"dyknow/{trust.federation}/v{WIRE_VERSION}/df/{platform}"  # as wire_key makes it
    count = 0
    first: tuple[str | None, str] | None = None
    answered = False
    for _ in range(tries):
        nonce = make_nonce()
        query = orjson.dumps({"v": WIRE_VERSION, "nonce": base64.b64encode(nonce).decode()})
        try:
            # the first signed answer ends the query (over MQTT it would last its timeout)
            async with await transport.ask(key, query, timeout=timeout) as replies:
                async for reply in replies:
                    if not reply.ok:
                        continue
                    try:
                        auth.open(reply.payload, "df", platform=platform, nonce=nonce)
                    except DirectoryStatementError as exc:
                        count += 1
                        if first is None:
                            first = (exc.platform, exc.reason[:200])
                        if refused is not None and count <= RUNS_REFUSED_KEPT:
                            refused.append((exc.platform, exc.reason[:200]))
                        continue
                    answered = True
                    break
        except TransportError as exc:
            log.debug("asking %s whether it runs: %s", platform, exc)
        if answered:
            break
    if first is not None:
        claimed, why = first
        log.warning(
            "asking whether %r runs: %d directory answer(s) in its name refused (the first "
            "from a platform calling itself %r: %s)%s",
            platform,
            count,
            claimed,
            why,
            "" if answered else "; no answer signed with its key",
        )
    return answered


def _df_of(agent: Agent, df: str | None) -> str:
    return df or f"df@{agent.platform.name}"


async def _ask_df(agent: Agent, df: str | None, content: dict[str, Any], timeout: float) -> Any:
    """The DF's answer to a FIPA-Agent-Management request (the platform's DF unless ``df``)."""
    return await request(
        agent, _df_of(agent, df), content, ontology=FIPA_AGENT_MANAGEMENT, timeout=timeout
    )


async def register_service(
    agent: Agent,
    service: ServiceDescription,
    *,
    df: str | None = None,
    timeout: float = DEFAULT_TIMEOUT,
) -> None:
    """Register ``agent``'s ``service`` with its platform's DF (or ``df``) over ACL."""
    await _ask_df(agent, df, {"action": "register", "service": service.to_obj()}, timeout)


async def modify_service(
    agent: Agent,
    service: ServiceDescription,
    *,
    df: str | None = None,
    timeout: float = DEFAULT_TIMEOUT,
) -> None:
    """Replace ``agent``'s registered service of the same name over ACL."""
    await _ask_df(agent, df, {"action": "modify", "service": service.to_obj()}, timeout)


async def deregister_service(
    agent: Agent,
    name: str | None = None,
    *,
    df: str | None = None,
    timeout: float = DEFAULT_TIMEOUT,
) -> int:
    """Deregister ``agent``'s service ``name`` (all of them when None); how many went."""
    content: dict[str, Any] = {"action": "deregister"}
    if name is not None:
        content["name"] = name
    n = await _ask_df(agent, df, content, timeout)
    return n if isinstance(n, int) else 0


async def search_services(
    agent: Agent,
    query: ServiceQuery | dict[str, Any] | None = None,
    *,
    df: str | None = None,
    scope: str = "local",
    timeout: float = DEFAULT_TIMEOUT,
    **fields: Any,
) -> list[ServiceDescription]:
    """Search a DF over ACL (``scope="global"``: its global view); the services it lets us see."""
    q = _query(query, fields)
    found = await _ask_df(
        agent,
        df,
        {
            "action": "search",
            "query": q.model_dump(mode="json", exclude_defaults=True),
            "scope": scope,
        },
        timeout,
    )
    if not isinstance(found, list):
        raise ServiceError(f"the DF answered a search with {found!r}")
    return [ServiceDescription.model_validate(s) for s in found]


async def subscribe_services(
    agent: Agent,
    query: ServiceQuery | dict[str, Any] | None = None,
    *,
    df: str | None = None,
    timeout: float = DEFAULT_TIMEOUT,
    **fields: Any,
) -> SubscriptionStream:
    """FIPA-Subscribe to a DF's changes matching ``query``: informs ``{"op", "service"}``."""
    q = _query(query, fields)
    return await subscribe(
        agent,
        _df_of(agent, df),
        q.model_dump(mode="json", exclude_defaults=True),
        ontology=FIPA_AGENT_MANAGEMENT,
        timeout=timeout,
    )
