"""The DyKnow Federation Agent: the DyKnow Federation service of one platform.

An agent (``federation@<platform>`` by default) on every platform of a federation lets
other platforms find and share what its local DyKnow instance knows, in *semantic*
labels only: each label is translated to a local one here (`LabelTranslator`) and local
labels never leave the platform, not even in a refusal.

Messages are FIPA ACL with ontology ``dyknow-federation`` and JSON content. Times are
seconds on the provider's time line, or relative to its now when the content says
``"relative": true`` (``"from": -120`` = the last two minutes). ``labels`` may also be
spelled ``semantic-labels`` (as in the paper).

FIPA-Request actions (answered ``inform``, or ``refuse`` with the reason):

* ``{"action": "create-stream", "labels": [s…], "from": t, "to": t, "sample-period": p,
  "max-delay": d, "relative": bool, "to-units": [platform…], "policy": {…}}`` → the
  sharing rules checked for the requester and each receiver (`Sharing`), every label
  translated (an unknown one is refused, naming it), the export limits checked (global
  and per requesting platform: ``too many exports``, ``too much history``), each
  receiver other than the requester asked to agree (``accept-stream``, below), a policy
  built (``policy`` may add the gateway's other policy fields: ``approximation``,
  ``change``, ``order``, ``late``, ``lower``, ``upper``), and the `Exporter` starts
  exporting each label to each receiving platform (default: the requester's). Inform:
  ``{"id": "x-…", "labels": [s…], "to-units": [platform…]}``. An exporter that fails
  answers ``failure`` (what was started is stopped again).
* ``{"action": "accept-stream", "requester": platform, "labels": [s…]}`` → from a
  provider, before it streams to this platform what ``requester`` asked for it: agreed
  (inform ``{"accepted": [s…]}``, and the streams are then expected here) only if
  ``consent`` allows it and, when the requester is not the provider, the requester
  confirms it asked; refused otherwise (the provider then refuses the create-stream).
* ``{"action": "confirm-stream", "provider": platform, "labels": [s…]}`` → from a
  receiver asked to accept streams this platform asked ``provider`` for it: inform
  ``{"confirmed": [s…]}`` if this platform's Federation Agent did ask so, else refuse.
* ``{"action": "cancel-stream", "id": "x-…"}`` → the export stops; inform
  ``{"cancelled": id}``. Allowed to agents of the requester's platform, of a receiving
  platform, and of this one. A FIPA ``cancel`` in the create-stream's conversation, from
  its requester, does the same, also while the create-stream is still being done (the
  export stops once started); `create_stream` sends one when it gives up waiting.
* ``{"action": "get-latest", "labels": [s…]}``,
  ``{"action": "get-value-at", "labels": [s…], "t": t, "approximation":
  "most_recent"|"closest"|"linear"}``,
  ``{"action": "get-trajectory", "labels": [s…], "from": t, "to": t}`` (each with
  ``relative``; ``from``/``to`` left out: unbounded / now) → inform
  ``{s: {"query_time": t, "samples": [[value, valid s, available s], …]}, …}``. One
  unknown label refuses the whole query. ``to-units`` (as the paper writes it) may only
  name the asker's platform: answers go to the asker.
* ``{"action": "search-labels", "formula": "(all ?x (and (Car ?x) (Color ?x blue)))"}`` →
  inform ``{"labels": [s…]}`` (`LabelSearch`); a malformed formula is refused with the
  parser's message (it names the position).
* ``{"action": "list-labels"}`` → inform ``{"labels": [s…]}``: what this platform provides
  (to another platform: what it may query or stream). Refusals by a sharing rule, consent
  or limit are counted in ``refusals`` and audited (``docs/federation.md``).
* ``{"action": "global-request", "request": {…}, "deadline": s, "select":
  "first"|"newest", "include-self": bool}`` → a `FederationAgent.global_request` on the
  asker's behalf; inform `GlobalResult.to_content`. Agents of this platform only.

FIPA-Query (query-ref) answers the reading actions (``get-*``, ``search-labels``,
``list-labels``) the same way.

FIPA-Subscribe with content ``{"membership": true}`` → ``agree``, then one inform
``{"event": "joined"|"left"|"gone", "platform": p}`` per membership change (Python code
uses `FederationAgent.membership`).

Membership. The paper makes the service *protected*: other platforms use it only
through the Interface Agent, which authenticates, checks access and audits every
message. But only *public* services appear in the global directory, and the global
directory is how platforms find each other. So the agent registers two entries of type
``dyknow-federation``: the service itself, protected, in the local DF (what local agents
find), and a public *discovery* entry (name ``<service>-discovery``) so the platform is
listed federation-wide. The public entry grants no path around the Interface Agent:
every message from another platform arrives through it whatever the visibility.
`FederationAgent.join` registers both, `FederationAgent.leave` deregisters both (the
Interface Agent then refuses requests from other platforms); exports already agreed
keep flowing after a leave, since the proxies talk directly. A platform whose presence
goes (crash, kill) is reported ``gone`` at once (the global directory follows liveliness
tokens); exports to it are stopped and its subscriptions dropped.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import time
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple, Protocol

from pydantic import JsonValue

from agents import (
    DEFAULT_TIMEOUT,
    FIPA_QUERY,
    FIPA_REQUEST,
    FIPA_SUBSCRIBE,
    LATER,
    ACLMessage,
    Agent,
    DirectoryEvent,
    DirectoryFacilitator,
    Failure,
    GlobalDirectory,
    HandedOver,
    MessageTemplate,
    Performative,
    Publisher,
    Refuse,
    Refused,
    ReplyTimeout,
    ServiceDescription,
    ServiceError,
    TokenBucket,
    Visibility,
    agent_id,
    new_id,
    on_query,
    on_request,
    platform_of,
    reason_of,
    request,
)
from agents.transports import Inbox, Subscription
from dyknow_core import DyKnowError, DyKnowInstance, Policy, PolicyError, UnknownLabelError
from ontology import LabelMapping, PlatformLabels, Vocabulary

from ._gateway_service import (
    GatewayRefusal,
    GatewayService,
    answer_content,
    contents_plain,
    jsonable,
    latest_contents_plain,
)
from ._gateway_service import Query as GatewayQuery
from ._quote import quoted
from ._service_content import (
    ONTOLOGY,
    QUERY_ACTIONS,
    AcceptStream,
    CancelStream,
    ConfirmStream,
    ContentError,
    CreateStream,
    GetLatest,
    GetTrajectory,
    GetValueAt,
    GlobalRequest,
    ListLabels,
    Query,
    Request,
    SearchLabels,
    latest_labels,
    newest_valid_time,
    parse_request,
)
from ._sharing import Sharing

log = logging.getLogger(__name__)

_only_str = frozenset({str}).issuperset

P = Performative

FEDERATION_AGENT = "federation"
"""The name of the DyKnow Federation Agent on every platform."""

FEDERATION_SERVICE_TYPE = "dyknow-federation"
"""The Directory Facilitator service type of the DyKnow Federation service."""

ACCEPT_RATE, ACCEPT_BURST = 2.0, 10.0
"""accept-stream requests per providing platform per second (bursts) this platform checks
with their requester; past it they are refused unasked (else a reflection). The same
budget bounds, per requesting platform, the create-streams for third platforms whose
receivers a provider asks (accept-stream)."""

UNSHARED_WHY = "the provider's sharing policy no longer allows it"
"""What a receiver's end marker says when a reloaded policy ends its export (the rule and
the config file are the provider's own: its log and audit have them)."""

MAX_MEMBERSHIP_SUBSCRIPTIONS = 16
"""Membership subscriptions one other platform may hold here (each event informs each)."""

# the labels (counted in the lists asked) whose translation a provider keeps: any member
# may ask for new lists of valid labels (a pattern's), and each label may be 200 characters
_MAX_RESOLVED = 2048
_MAX_CANCELLED_EARLY = 256  # cancels kept for a create-stream not taken up yet (a member
# may send cancels in conversations that never had one: the oldest are forgotten)
_MAX_CANCELLED_EARLY_BY_SENDER = 16  # of them, one sender's: its flood forgets only its own

__all__ = [
    "FEDERATION_AGENT",
    "FEDERATION_SERVICE_TYPE",
    "ONTOLOGY",
    "Anchor",
    "Consent",
    "Exporter",
    "FederationAgent",
    "GlobalResult",
    "ImportAgreements",
    "LabelSearch",
    "LabelTranslator",
    "MembershipEvent",
    "StreamExport",
]


# -- what the service needs from the ontology and the proxies ---------------------------


class LabelTranslator(Protocol):
    """Semantic ↔ local labels of this platform (the ontology's label mapping)."""

    def to_local(self, semantic: str, /) -> str:
        """The local label of ``semantic``; raises when unknown (its text is the reason)."""
        ...

    def to_semantic(self, local: str, /) -> str:
        """The semantic label of local label ``local``; raises when it has none."""
        ...

    def provides(self) -> Iterable[str]:
        """The semantic labels this platform can provide now."""
        ...


class _Durable:
    """A durable stream: what was asked, and the provider's export id for it now."""

    # a plain class, not a dataclass: generating a dataclass's methods costs ~0.4 ms of a
    # node's start, each; nothing compares or prints these
    __slots__ = ("content", "current")

    def __init__(self, content: dict[str, Any], current: str) -> None:
        self.content = content
        self.current = current


DURABLE_TRIES = 6
"""How often a durable stream is asked for again when its provider comes back."""

Anchor = Callable[[str, str, str], Awaitable[bool]]
"""``anchor(semantic, local, requester)``: asked to export a label with no stream here yet.

The application may anchor the object (e.g. get its trajectory from ``requester`` and
look for it), create the local stream ``local`` and return True; False refuses.
"""


class LabelSearch(Protocol):
    """Finds semantic labels by an FIPA-SL formula (the ontology's label search)."""

    def find(self, formula: str, /) -> list[str]:
        """The labels ``formula`` describes; raises on a malformed one (text: the position)."""
        ...


class ImportAgreements(Protocol):
    """The streams this platform agreed to receive (the import proxy accepts only these)."""

    def expect(self, sender: str, semantic: str, /) -> object:
        """Agree to receive ``sender``'s stream of ``semantic``; raises if it cannot land here."""
        ...

    def accept(
        self, sender: str, semantic: str, requester: str, /, *, pending: bool = False
    ) -> object:
        """Agree to a stream ``requester`` asked ``sender`` for here: bounded per sender and
        per (sender, requester), and withdrawn if it does not start within a lease (also
        when ``pending``, agreed only by a request of ours not answered yet); raises if it
        cannot land here or a bound is reached."""
        ...

    def agreed(self, sender: str, semantic: str, /) -> bool:
        """Whether ``sender``'s stream of ``semantic`` is agreed here already."""
        ...

    def withdraw(self, sender: str, semantic: str, /, *, gave_up: bool = False) -> object:
        """Undo `expect` after the request failed: the stream ends here, if samples landed
        (``gave_up``: we stopped waiting and cancel the export)."""
        ...


_Held = tuple[str, str, bool]
"""(provider, label, counted) a create-stream of ours expects: see `_expect_from`."""

Consent = Callable[[str, str, list[str]], str | None]
"""``consent(requester, provider, labels)``: None to receive the streams, else why not."""


class Denied(ContentError):
    """A request refused by a rule or a limit: counted by ``code`` and audited."""

    def __init__(self, code: str, reason: str) -> None:
        super().__init__(reason)
        self.code = code


class Exporter(Protocol):
    """Starts and stops exports (the export proxy); either method may be async."""

    def start_exporting(
        self,
        local_label: str,
        semantic_label: str,
        receiver: str,
        policy: Policy,
        /,
        *,
        history: int = 0,
    ) -> object:
        """Export ``local_label`` as ``semantic_label`` to ``receiver`` (keeping ``history``)."""
        ...

    def stop(self, export: Any, /, *, why: str | None = None) -> object:
        """Stop an export that `start_exporting` returned (``why``: told to its receiver)."""
        ...


async def _resolved(value: Any) -> Any:
    """``value``, awaited when it is awaitable (the protocols allow sync and async)."""
    if inspect.isawaitable(value):
        return await value
    return value


def _reason(exc: BaseException) -> str:
    """The text of an error from a collaborator, as a refusal carries it."""
    # Not ``exc.reason``: the ontology's errors keep a short code there, the text in str().
    if isinstance(exc, KeyError) and len(exc.args) == 1 and type(exc).__str__ is KeyError.__str__:
        return str(exc.args[0])  # KeyError's own str() quotes the message
    return str(exc) or type(exc).__name__


def _about(label: str, reason: str) -> str:
    """``reason``, naming ``label`` if it does not already."""
    return reason if label in reason else f"label {label!r}: {reason}"


# -- results and records ------------------------------------------------------------------


class MembershipEvent(NamedTuple):
    """A membership change: ``kind`` is ``joined``, ``left`` or ``gone``."""

    kind: Literal["joined", "left", "gone"]
    platform: str


@dataclass(slots=True)
class StreamExport:
    """One agreed create-stream: who asked, which labels go to which platforms."""

    id: str
    requester: str
    conversation_id: str | None
    labels: list[str]
    receivers: list[str]
    policy: Policy
    history: int = 0
    handles: dict[tuple[str, str], Any] = field(default_factory=dict)
    """(semantic label, receiver) → the exporter's handle."""


Fuse = Callable[[dict[str, JsonValue]], Any]
"""Fuses the answers of a global request: {platform: inform content} → one value."""

Select = Literal["first", "newest"] | Fuse


@dataclass(slots=True)
class GlobalResult:
    """How a global request went: every answer, the selected (or fused) value, who failed.

    ``answers`` keeps arrival order. ``chosen`` names the platform whose answer is
    ``value`` (None when fused, or when nobody answered). ``refused`` holds the reasons
    of those that refused, failed or could not be reached; ``no_answer`` the platforms
    silent until the deadline; ``unlisted`` the members not asked because the global
    directory does not list their federation service (yet): their signed snapshot has not
    been read, so whom to ask there is not known.
    """

    asked: list[str] = field(default_factory=list)
    answers: dict[str, JsonValue] = field(default_factory=dict)
    refused: dict[str, str] = field(default_factory=dict)
    no_answer: list[str] = field(default_factory=list)
    unlisted: list[str] = field(default_factory=list)
    value: Any = None
    chosen: str | None = None

    def to_content(self) -> dict[str, Any]:
        """The result as ACL content (keys as the service's other content: hyphenated)."""
        return {
            "value": jsonable(self.value),
            "chosen": self.chosen,
            "answers": self.answers,
            "refused": self.refused,
            "no-answer": self.no_answer,
            "unlisted": self.unlisted,
            "asked": self.asked,
        }


# -- the agent ----------------------------------------------------------------------------


class FederationAgent(Agent):
    """The DyKnow Federation Agent: streams, queries, label search, global requests, membership.

    ``instance`` is the local DyKnow instance, ``translator`` maps semantic labels to
    local ones, ``exporter`` starts exports (without one, create-stream is refused) and
    ``search`` finds labels by formula (without one, search-labels is refused). At most
    ``max_exports`` exports (a label to a receiver) run at once, at most
    ``max_exports_per_platform`` of them asked by one platform, keeping at most
    ``max_history_per_platform`` samples of history for it. ``sharing`` says who may
    query or stream which label (default: every member, every label). ``imports`` records
    the streams this platform agreed to receive: those it asks for itself (withdrawn
    when the request fails), and those ``consent(requester, provider, labels)`` accepts
    when another platform asks a provider to stream here (``imports.accept``: bounded,
    and withdrawn if they do not start; without ``consent``: none).
    ``join=False`` leaves the platform out of the federation until `join`. Refusals by
    rule or limit are counted in ``refusals`` (by code) and audited.
    """

    def __init__(
        self,
        instance: DyKnowInstance,
        translator: LabelTranslator,
        *,
        exporter: Exporter | None = None,
        search: LabelSearch | None = None,
        name: str = FEDERATION_AGENT,
        service_name: str = "dyknow-federation",
        max_exports: int = 64,
        max_exports_per_platform: int | None = None,
        max_history_per_platform: int | None = None,
        sharing: Sharing | None = None,
        imports: ImportAgreements | None = None,
        consent: Consent | None = None,
        join: bool = True,
        stop_exports_to_gone: bool = True,
        anchor: Anchor | None = None,
    ) -> None:
        super().__init__(name)
        self.max_exports_per_platform = max_exports_per_platform
        self.max_history_per_platform = max_history_per_platform
        self.sharing = sharing if sharing is not None else Sharing()
        self.imports = imports
        self.consent = consent
        self.refusals: dict[str, int] = {}
        self._reserved_by: dict[str, int] = {}  # exports being started, per requester
        self._history_reserved_by: dict[str, int] = {}  # and the history they will keep
        # (provider, receiver, label) -> how many of our create-streams asked it for others
        self._for_others: dict[tuple[str, str, str], int] = {}
        self._for_others_by: dict[tuple[str, str], list[tuple[str, str, str]]] = {}
        # provider -> its accept-stream budget (one per authenticated platform)
        self._accept_buckets: dict[str, TokenBucket] = {}
        # requester -> its budget of create-streams that make us ask third platforms
        self._consent_buckets: dict[str, TokenBucket] = {}
        self.instance = instance
        self.anchor = anchor
        self.translator = translator
        self.exporter = exporter
        self.label_search = search
        self.gateway = GatewayService(instance)
        self.service_name = service_name
        self.max_exports = max_exports
        self.stop_exports_to_gone = stop_exports_to_gone
        self._join_on_setup = join
        self._exports: dict[str, StreamExport] = {}
        self._by_conversation: dict[tuple[str, str], str] = {}
        # (requester, conversation) -> cancelled: create-streams not answered yet; one its
        # requester cancels meanwhile (it gave up waiting) is stopped once started
        self._creating: dict[tuple[str, str], bool] = {}
        # (requester, conversation) of cancels that came before their create-stream was
        # taken up: both were in the mailbox at once (a requester that gave up at once),
        # and the create-stream's task had not run yet when the cancel was routed
        self._cancelled_early: dict[tuple[str, str], None] = {}
        self._reserved = 0
        # (provider, label) -> how many of our create-streams not yet answered expect it,
        # agreed by nothing else: withdrawn when none of them is accepted (`_settle`)
        self._tentative: dict[tuple[str, str], int] = {}
        # provider -> the id create_stream returned -> what was asked, the export id now
        self._durable: dict[str, dict[str, _Durable]] = {}
        self._asking: dict[str, asyncio.Lock] = {}  # one re-ask at a time per provider
        self._members: set[str] = set()
        self._watchers: list[Inbox[MembershipEvent]] = []
        self._directory: Subscription[DirectoryEvent] | None = None
        # include_self -> (the directory, its version, `providers` of it): asked per request
        self._providers: dict[bool, tuple[GlobalDirectory, int, dict[str, str]]] = {}
        # the labels of a get-latest as asked -> (each once, their local labels, all str):
        # kept while the translator, its mapping and vocabulary are those of
        # ``_resolved_by`` (`_remember`); a provider is asked the same lists again
        self._resolved: dict[tuple[Any, ...], tuple[list[str], list[str], bool]] = {}
        self._resolved_by: tuple[PlatformLabels, LabelMapping, Vocabulary] | None = None
        self._resolved_labels = 0  # bounds `_resolved` (`_MAX_RESOLVED`): members pick the lists
        # the two above as one reference, replaced whole: what `answer_on_thread` reads
        self._resolved_view: (
            tuple[
                tuple[PlatformLabels, LabelMapping, Vocabulary],
                dict[tuple[Any, ...], tuple[list[str], list[str], bool]],
            ]
            | None
        ) = None
        self._subscribers = Publisher(self, ontology=ONTOLOGY, accept=self._accept_subscriber)
        # a subclass may add handlers (matched first) or checks: its handlers decide all
        self._at_once = type(self) is FederationAgent
        self.add_handler(
            MessageTemplate(P.CANCEL, ontology=ONTOLOGY, where=self._is_export_cancel),
            self._on_cancel,
        )

    # -- lifecycle and membership -------------------------------------------------------

    def descriptions(self) -> list[ServiceDescription]:
        """The two entries this agent registers: the protected service, the public discovery."""
        protocols = [FIPA_REQUEST, FIPA_QUERY, FIPA_SUBSCRIBE]
        return [
            ServiceDescription(
                name=self.service_name,
                type=FEDERATION_SERVICE_TYPE,
                provider=self.aid,
                ontology=ONTOLOGY,
                protocols=protocols,
                properties={"entry": "service"},
                visibility=Visibility.PROTECTED,
            ),
            ServiceDescription(
                name=f"{self.service_name}-discovery",
                type=FEDERATION_SERVICE_TYPE,
                provider=self.aid,
                ontology=ONTOLOGY,
                protocols=protocols,
                properties={"entry": "discovery"},
                visibility=Visibility.PUBLIC,
            ),
        ]

    async def setup(self) -> None:
        """Follow the global directory, then join (unless told not to)."""
        gdf = self.platform.global_df
        if gdf is not None:
            # Watch before reading the members: a change in between is queued, not lost.
            self._directory = gdf.watch()
            self._members = {s.platform for s in gdf.search(type=FEDERATION_SERVICE_TYPE)}
            self.spawn(self._follow_directory(self._directory), "membership")
        if self._join_on_setup:
            await self.join()

    async def teardown(self) -> None:
        """End subscriptions and membership streams; stop the exports this agent agreed."""
        if self._directory is not None:
            self._directory.close()
        for inbox in self._watchers:
            inbox.close()
        self._watchers.clear()
        await self._subscribers.end()
        for record in list(self._exports.values()):
            await self._end(record)

    def _df(self) -> DirectoryFacilitator:
        df = self.platform.df
        if df is None:
            raise ServiceError(f"platform {self.platform.name} has no Directory Facilitator")
        return df

    @property
    def joined(self) -> bool:
        """Whether this platform's service is registered (it is a federation member)."""
        df = self.platform.df
        name = f"{self.service_name}-discovery"
        return df is not None and df.service_of_agent(self.aid, name) is not None

    async def join(self) -> None:
        """Register the service (protected) and its discovery entry (public)."""
        df = self._df()
        for service in self.descriptions():
            if df.service_of_agent(self.aid, service.name) is None:
                await df.register(service)

    async def leave(self) -> None:
        """Deregister both entries; exports already agreed keep flowing."""
        df = self._df()
        for service in self.descriptions():
            await df.deregister(self.aid, service.name)

    @property
    def members(self) -> list[str]:
        """The members now: the platforms whose federation service the signed directory
        events announced, one not yet listed (`GlobalDirectory.listed`) included."""
        return sorted(self._members)

    def membership(self, maxlen: int = 1024) -> Subscription[MembershipEvent]:
        """An async iterator of membership changes (joined, left, gone) from now on."""
        inbox: Inbox[MembershipEvent] = Inbox(asyncio.get_running_loop(), maxlen)
        self._watchers.append(inbox)

        def remove() -> None:
            if inbox in self._watchers:
                self._watchers.remove(inbox)

        return Subscription(inbox, remove)

    def _accept_subscriber(self, message: ACLMessage) -> None:
        if message.content != {"membership": True}:
            raise Refuse('subscribe with {"membership": true}')
        asker = platform_of(message.sender)
        if asker == self.platform.name:
            return
        # bounded per platform: every membership event informs every subscriber, so
        # unbounded subscriptions would cost memory and make each event a flood
        key = (message.sender, message.conversation_id or "")
        held = sum(
            1 for k in self._subscribers.subscribers if k != key and platform_of(k[0]) == asker
        )
        if held >= MAX_MEMBERSHIP_SUBSCRIPTIONS:
            exc = Denied(
                "subscription-limit",
                f"too many membership subscriptions for {asker} (limit "
                f"{MAX_MEMBERSHIP_SUBSCRIPTIONS}: {held} held)",
            )
            self._denied(message, exc)
            raise Refuse(exc.reason)

    async def _follow_directory(self, events: Subscription[DirectoryEvent]) -> None:
        async for event in events:
            try:
                await self._on_directory_event(event)
            except Exception:
                log.exception("%s: handling %s of %s failed", self, event.op, event.platform)

    async def _on_directory_event(self, event: DirectoryEvent) -> None:
        platform = event.platform
        if event.op == "platform-gone":
            self._members.discard(platform)
            await self._platform_gone(platform)
            return
        service = event.service
        if service is None or service.type != FEDERATION_SERVICE_TYPE:
            return
        if event.op in ("register", "modify") and platform not in self._members:
            self._members.add(platform)
            await self._announce("joined", platform)
        elif event.op == "deregister" and platform in self._members:
            gdf = self.platform.global_df
            still = gdf is not None and any(
                s.type == FEDERATION_SERVICE_TYPE for s in gdf.services(platform)
            )
            if not still:
                self._members.discard(platform)
                await self._announce("left", platform)

    async def _platform_gone(self, platform: str) -> None:
        # Its subscribers cannot be told any more: drop them before announcing.
        subscribers = self._subscribers.subscribers
        for key in [k for k in subscribers if platform_of(k[0]) == platform]:
            del subscribers[key]
        await self._announce("gone", platform)
        if self.stop_exports_to_gone:
            await self._stop_exports_to(platform)

    async def _announce(self, kind: Literal["joined", "left", "gone"], platform: str) -> None:
        if kind == "joined" and self._durable.get(platform):
            self.spawn(self._ask_again(platform), f"durable:{platform}")
        event = MembershipEvent(kind, platform)
        for inbox in list(self._watchers):
            inbox.put(event)
        await self._subscribers.publish({"event": kind, "platform": platform})

    def export_ended(self, provider: str, semantic: str) -> None:
        """``provider`` ended its export of ``semantic`` by itself: ask durable ones again."""
        if any(semantic in d.content["labels"] for d in self._durable.get(provider, {}).values()):
            self.spawn(self._ask_again(provider, semantic), f"durable:{provider}:{semantic}")

    async def _ask_again(self, provider: str, semantic: str | None = None) -> None:
        """Create the durable streams from ``provider`` anew (it came back, or ended them)."""
        lock = self._asking.setdefault(provider, asyncio.Lock())
        async with lock:  # two quick returns must not ask twice for the same stream
            asked = self._durable.get(provider, {})
            for first_id, entry in list(asked.items()):
                if semantic is None or semantic in entry.content["labels"]:
                    await self._ask_one(provider, first_id, entry)

    async def _ask_one(self, provider: str, first_id: str, entry: _Durable) -> None:
        for attempt in range(DURABLE_TRIES):
            if provider not in self._members:
                return  # gone again: its next return asks again
            try:
                answer = await self.request_from(provider, entry.content)
            except Refused as exc:
                if "cancel it first" in str(exc):
                    return  # it still runs there (the provider only left and came back)
                # the provider's words: on one line, bounded
                log.info(
                    "%s: asking %s again for %s: %s", self, provider, entry.content, quoted(exc)
                )
            except Exception as exc:
                # its agents may still be starting (key exchange, directory)
                log.info(
                    "%s: asking %s again for %s: %s", self, provider, entry.content, quoted(exc)
                )
            else:
                new_id = str(answer["id"])
                if self._durable.get(provider, {}).get(first_id) is not entry:
                    # cancelled while we asked: the new export must not outlive it
                    try:
                        await self.request_from(provider, {"action": "cancel-stream", "id": new_id})
                    except Exception as exc:  # it ends with its lease there
                        log.info("%s: cancelling %s at %s: %s", self, new_id, provider, quoted(exc))
                    return
                entry.current = new_id
                log.info("%s: %s created again by %s", self, entry.content["labels"], provider)
                return
            await asyncio.sleep(min(2.0, 0.25 * 2**attempt))

    # -- requests -----------------------------------------------------------------------

    def _plain_get_latest(self, message: ACLMessage) -> list[str] | None:
        """The labels of a plain get-latest this agent may answer at once; else None."""
        if (
            not self._at_once
            or message.ontology != ONTOLOGY
            or (message.performative is not P.QUERY_REF and message.performative is not P.REQUEST)
        ):
            return None
        return latest_labels(message.content)

    def answer_at_once(self, message: ACLMessage) -> Any:
        """A plain get-latest of another platform answered as it comes; anything else `LATER`.

        What `_on_request` and `_on_query` answer to it, without the mailbox and a task:
        it reads the latest samples and changes nothing. A refusal (a sharing rule, a
        label not here) is left to them, so it is counted and audited as always.
        """
        labels = self._plain_get_latest(message)
        if labels is None:
            return LATER
        try:
            return self._latest_reply(labels, platform_of(message.sender))
        except Exception:
            return LATER

    def answer_on_thread(self, message: ACLMessage) -> Any:
        """`answer_at_once` on zenoh's thread: from what the event loop replaces whole, or `LATER`.

        The labels' translation kept by `_remember` (one reference), the sharing settings
        (read once, the default class's check only) and each stream's latest sample
        (`DyKnowInstance.latest_many_now`): a get-latest asked for the first time, a
        refusal, a sample not yet available, go to `answer_at_once` on the loop.
        """
        asked = self._plain_get_latest(message)
        view = self._resolved_view
        if asked is None or view is None:
            return LATER
        by, resolved = view
        translator = self.translator
        if by[0] is not translator or by[1] is not translator.mapping:
            return LATER
        if by[2] is not by[1].vocabulary:
            return LATER
        kept = resolved.get(tuple(asked))
        if kept is None:
            return LATER
        labels, local, only_str = kept
        asker = platform_of(message.sender)
        if asker != self.platform.name:
            sharing = self.sharing
            if type(sharing) is not Sharing:
                return LATER  # a subclass's check (or check_all) may read the loop's state
            if sharing.check_all("query", labels, asker) is not None:
                return LATER  # refused on the loop, counted and audited there
        read = self.instance.latest_many_now(local)
        if read is None:
            return LATER
        contents, plain = contents_plain(*read)
        answer = dict(zip(labels, contents, strict=True))
        if plain and only_str:
            return HandedOver(answer)
        return answer

    @on_request(ONTOLOGY, concurrent=True)
    async def _on_request(self, message: ACLMessage) -> Any:
        """Every action of the service: its result, or refuse with the reason."""
        try:
            # the common request, a plain get-latest, without its model (`latest_labels`)
            labels = latest_labels(message.content)
            if labels is not None:
                return self._latest_reply(labels, platform_of(message.sender))
            return await self._perform(parse_request(message.content), message)
        except Denied as exc:
            self._denied(message, exc)
            raise Refuse(exc.reason) from exc
        except ContentError as exc:
            raise Refuse(exc.reason) from exc

    @on_query(ONTOLOGY)
    async def _on_query(self, message: ACLMessage) -> Any:
        """query-ref for the reading actions (get-*, search-labels, list-labels)."""
        if message.performative is P.QUERY_IF:
            raise Refuse("the federation service answers query-ref, not query-if")
        try:
            labels = latest_labels(message.content)  # as in `_on_request`
            if labels is not None:
                return self._latest_reply(labels, platform_of(message.sender))
            req = parse_request(message.content)
            if req.action not in QUERY_ACTIONS and req.action != "list-labels":
                raise ContentError(f"{req.action} is an action: ask for it with FIPA-Request")
            return await self._perform(req, message)
        except Denied as exc:
            self._denied(message, exc)
            raise Refuse(exc.reason) from exc
        except ContentError as exc:
            raise Refuse(exc.reason) from exc

    def _denied(self, message: ACLMessage, exc: Denied) -> None:
        """Count and audit a refusal by rule or limit (the Interface Agent admitted it): one
        by one within the asking platform's budget, the rest summed up."""
        self.refusals[exc.code] = self.refusals.get(exc.code, 0) + 1
        # a member may repeat a request a rule, consent or limit refuses at its rate limit
        # (past the consent rate, each is refused at once): a record and a log line each
        # would flood both, so only those within its budget get them
        if self.platform.audit_refused(message, "federation", exc.code, exc.reason):
            # the reason may quote what the requester asked for (a label, a formula): bounded
            log.info("%s: refused %s: %s", self, message.sender, quoted(exc.reason))

    async def _perform(self, req: Request, message: ACLMessage) -> Any:
        if isinstance(req, CreateStream):
            return await self._create_stream(req, message)
        if isinstance(req, CancelStream):
            return await self._cancel_stream(req.id, message.sender)
        if isinstance(req, GetLatest | GetValueAt | GetTrajectory):
            return self._query(req, message.sender)
        if isinstance(req, SearchLabels):
            found = self._search(req.formula)
            return {"labels": self._visible(found["labels"], message.sender)}
        if isinstance(req, ListLabels):
            provided = sorted(set(self.translator.provides()))
            return {"labels": self._visible(provided, message.sender)}
        if isinstance(req, AcceptStream):
            return await self._accept_stream(req, message.sender)
        if isinstance(req, ConfirmStream):
            return self._confirm_stream(req, message.sender)
        return await self._global_on_behalf(req, message)

    def _visible(self, labels: list[str], sender: str) -> list[str]:
        """The labels ``sender``'s platform may query or stream (all, for our own agents)."""
        asker = platform_of(sender)
        if asker == self.platform.name:
            return labels
        check = self.sharing.check
        return [s for s in labels if not check("query", s, asker) or not check("stream", s, asker)]

    def _check_sharing(self, action: Literal["query", "stream"], label: str, platform: str) -> None:
        if platform == self.platform.name:
            return
        reason = self.sharing.check(action, label, platform)
        if reason is not None:
            raise Denied("sharing-rule", reason)

    # -- consent: streams another platform asked to be sent here -------------------------

    async def _accept_stream(self, req: AcceptStream, sender: str) -> dict[str, Any]:
        """A provider asks whether we receive the streams ``req.requester`` asked it for."""
        provider = platform_of(sender)
        if provider == self.platform.name:
            raise ContentError("a platform does not export to itself")
        if req.requester == self.platform.name:
            # we asked: then our own Federation Agent expects it already, if we asked it
            raise Denied(
                "consent",
                f"{self.platform.name} asked {provider} for nothing of the kind: "
                "its streams are expected when it asks for them itself",
            )
        reason = (
            "this platform accepts no stream asked for it by another (no consent)"
            if self.consent is None
            else self.consent(req.requester, provider, list(req.labels))
        )
        if reason is not None:
            raise Denied("consent", reason)
        labels = list(dict.fromkeys(req.labels))
        if req.requester != provider:
            # each check is a request of ours to the requester: bounded per provider, or a
            # member could make this platform flood a third one in its name
            if not _take(self._accept_buckets, provider):
                raise Denied(
                    "consent-rate",
                    f"too many accept-stream requests from {provider} (at most "
                    f"{ACCEPT_RATE:g}/s, bursts of {ACCEPT_BURST:g}): not checked with "
                    f"{req.requester}",
                )
            # the provider only says who asked: the requester confirms it did
            await self._confirm_with(req.requester, provider, labels)
        imports = self.imports
        if imports is not None:
            new: list[str] = []  # refused after all: what this request agreed is withdrawn
            tentative = self._tentative
            for semantic in labels:
                try:
                    if (provider, semantic) in tentative:
                        # a request of ours for it waits: consented, it is leased (kept
                        # if that request fails, ours for good if it is accepted)
                        imports.accept(provider, semantic, req.requester, pending=True)
                    elif not imports.agreed(provider, semantic):
                        imports.accept(provider, semantic, req.requester)
                        new.append(semantic)
                except Denied as exc:  # a limit: counted and audited
                    for agreed in new:
                        self._withdraw(provider, agreed)
                    raise Denied(exc.code, _about(semantic, exc.reason)) from exc
                except Exception as exc:
                    for agreed in new:
                        self._withdraw(provider, agreed)
                    raise ContentError(_about(semantic, _reason(exc))) from exc
            for semantic in labels:
                # consented: a request of ours for it, waiting still, that fails leaves it
                # to the lease
                tentative.pop((provider, semantic), None)
        log.info("%s: agreed to receive %s from %s for %s", self, labels, provider, req.requester)
        return {"accepted": labels}

    async def _confirm_with(self, requester: str, provider: str, labels: list[str]) -> None:
        """Ask ``requester`` whether it asked ``provider`` for ``labels`` to this platform."""
        content = {"action": "confirm-stream", "provider": provider, "labels": labels}
        try:
            await self.request_from(requester, content)
        except Refused as exc:
            raise Denied(
                "consent",
                f"{requester} did not confirm it asked {provider} for {labels}: {quoted(exc)}",
            ) from exc
        except Exception as exc:
            raise ContentError(
                f"{requester} did not answer whether it asked {provider} for {labels}: "
                f"{quoted(reason_of(exc))}"
            ) from exc

    def _confirm_stream(self, req: ConfirmStream, sender: str) -> dict[str, Any]:
        """A receiver asks whether we asked ``req.provider`` to stream ``req.labels`` to it."""
        receiver = platform_of(sender)
        labels = list(dict.fromkeys(req.labels))
        missing = [s for s in labels if (req.provider, receiver, s) not in self._for_others]
        if missing:
            raise Denied(
                "consent",
                f"{self.platform.name} asked {req.provider} for no stream of {missing} "
                f"to {receiver}",
            )
        return {"confirmed": labels}

    async def _ask_consent(self, receiver: str, requester: str, labels: list[str]) -> None:
        """Ask ``receiver``'s Federation Agent to agree to the streams; Denied if it does not."""
        content = {"action": "accept-stream", "requester": requester, "labels": labels}
        try:
            await self.request_from(receiver, content)
        except Refused as exc:
            raise Denied(
                "consent",
                f"receiver {receiver} did not agree to receive {labels}: {quoted(exc)}",
            ) from exc
        except Exception as exc:
            raise ContentError(
                f"receiver {receiver} did not answer whether it receives {labels}: "
                f"{quoted(reason_of(exc))}"
            ) from exc

    def _translate(self, semantic: str) -> str:
        try:
            return self.translator.to_local(semantic)
        except Exception as exc:
            raise ContentError(_about(semantic, _reason(exc))) from exc

    # -- create-stream and cancel ---------------------------------------------------------

    @property
    def exports(self) -> dict[str, StreamExport]:
        """The exports agreed and running, by id."""
        self._prune_ended()
        return dict(self._exports)

    @property
    def export_count(self) -> int:
        """How many (label, receiver) exports run now."""
        self._prune_ended()
        return sum(len(r.handles) for r in self._exports.values())

    def _prune_ended(self) -> None:
        """Forget exports that ended by themselves (their `to` passed, their stream ended,
        the transport closed): they no longer hold a slot or block the same request."""
        for export_id, record in list(self._exports.items()):
            for key, handle in list(record.handles.items()):
                if getattr(handle, "active", True) is False:
                    del record.handles[key]
            if not record.handles:
                del self._exports[export_id]

    async def _await_listed(self, receivers: list[str], requester: str) -> None:
        """Wait (one directory query timeout at most) for receivers present but not listed.

        One that just joined is in `members` by its signed events before its snapshot
        answered: a requester that saw it there must not be refused in that gap. Bounded,
        so a forged presence token under a trusted name costs a request no more than that.
        """
        gdf = self.platform.global_df
        if gdf is None:
            return
        loop = asyncio.get_running_loop()
        deadline = loop.time() + gdf.query_timeout
        while True:
            listed = set(gdf.listed)
            present = set(gdf.platforms)  # its first snapshot asked now (not unconfirmed)
            if not any(w in present and w not in listed for w in receivers if w != requester):
                return
            if loop.time() >= deadline:
                return
            await asyncio.sleep(0.02)  # the directory tells no event for a listing

    def _check_receivers(self, receivers: list[str], requester: str) -> None:
        gdf = self.platform.global_df
        if gdf is None:
            return
        # listed only: one whose snapshot is still asked may be a forged presence token
        listed = set(gdf.listed)
        unknown = [w for w in receivers if w not in listed and w != requester]
        if unknown:
            # one present whose snapshot has not answered may have just joined (it can be in
            # `members` already, by its signed events): say so, the requester may ask again
            present = set(gdf.platforms) | set(gdf.unconfirmed)
            pending = [w for w in unknown if w in present]
            later = (
                f" ({', '.join(pending)} not listed here yet: present, its signed directory "
                "snapshot not answered; ask again once it is listed)"
                if pending
                else ""
            )
            raise Denied(
                "unlisted-receiver",
                f"unknown receiver {', '.join(unknown)}: not in the federation{later}",
            )

    def _check_new(self, pairs: list[tuple[str, str]], receivers: list[str]) -> None:
        if self.platform.name in receivers:
            raise ContentError("a platform does not export to itself")
        self._prune_ended()
        running = {key: r.id for r in self._exports.values() for key in r.handles}
        for semantic, _ in pairs:
            for receiver in receivers:
                if (semantic, receiver) in running:
                    raise ContentError(
                        f"{semantic!r} already goes to {receiver} "
                        f"(export {running[(semantic, receiver)]}): cancel it first"
                    )

    async def _create_stream(self, req: CreateStream, message: ACLMessage) -> dict[str, Any]:
        exporter = self.exporter
        if exporter is None:
            raise ContentError("this platform exports no streams")
        requester = platform_of(message.sender)
        receivers = list(dict.fromkeys(req.to_units or [requester]))
        sharing = self.sharing  # the policy checked: a reload while it starts checks again
        for semantic in dict.fromkeys(req.labels):
            for who in dict.fromkeys([requester, *receivers]):
                self._check_sharing("stream", semantic, who)
        pairs = [(s, self._translate(s)) for s in dict.fromkeys(req.labels)]
        await self._await_listed(receivers, requester)
        self._check_receivers(receivers, requester)
        self._check_new(pairs, receivers)
        try:
            policy = req.policy_spec().to_policy(self.instance.clock.now())
        except (PolicyError, ValueError, OverflowError) as exc:
            # Named as the content names them, not as the core does.
            reason = str(exc).replace("sample_period", "sample-period")
            raise ContentError(reason.replace("max_delay", "max-delay")) from exc
        needed = len(pairs) * len(receivers)
        self._check_limits(requester, needed, req.history)
        others = [w for w in receivers if w != requester]
        # each asks every other receiver (accept-stream): bounded, or a member could make
        # this platform send requests to third ones at will
        if (
            others
            and requester != self.platform.name
            and not _take(self._consent_buckets, requester)
        ):
            raise Denied(
                "consent-rate",
                f"too many create-streams for other platforms from {requester} (at "
                f"most {ACCEPT_RATE:g}/s, bursts of {ACCEPT_BURST:g}): "
                f"{', '.join(others)} not asked",
            )
        record = StreamExport(
            id=new_id("x"),
            requester=message.sender,
            conversation_id=message.conversation_id,
            labels=[s for s, _ in pairs],
            receivers=receivers,
            policy=policy,
            history=req.history,
        )
        # Reserved while the receivers agree and the exporter starts (both await): a
        # concurrent request must not slip under the limits meanwhile.
        self._reserved += needed
        self._reserved_by[requester] = self._reserved_by.get(requester, 0) + needed
        kept = req.history * needed
        self._history_reserved_by[requester] = self._history_reserved_by.get(requester, 0) + kept
        creating = None
        if message.conversation_id is not None:
            creating = (message.sender, message.conversation_id)
            # its requester's cancel may have been routed before this task ran
            early = creating in self._cancelled_early
            if early:
                del self._cancelled_early[creating]
            self._creating[creating] = early
        cancelled = False
        try:
            for receiver in receivers:
                if receiver != requester:
                    # a stream goes to a platform that did not ask only if it agrees
                    await self._ask_consent(receiver, requester, record.labels)
            for semantic, local in pairs:
                for receiver in receivers:
                    if self.sharing is not sharing:
                        # reloaded while this one started: the new policy decides before
                        # anything more is sent (those running stop, their receivers told)
                        await self._recheck(record, requester)
                    try:
                        handle = await self._start_export(
                            exporter, local, semantic, receiver, policy, requester, req.history
                        )
                    except UnknownLabelError as exc:
                        # Nothing to export (yet); its message lists local labels.
                        raise Refuse(f"label {semantic!r}: no stream for it here") from exc
                    except Exception as exc:
                        log.warning("%s: exporting %r to %s: %s", self, semantic, receiver, exc)
                        reason = _reason(exc).replace(local, semantic)
                        raise Failure(
                            f"exporting {semantic!r} to {receiver} failed: {reason}"
                        ) from exc
                    record.handles[(semantic, receiver)] = handle
        except BaseException:
            await self._stop_handles(record)
            raise
        finally:
            if creating is not None:
                cancelled = self._creating.pop(creating, False)
            self._reserved -= needed
            for table, n in ((self._reserved_by, needed), (self._history_reserved_by, kept)):
                left = table.get(requester, 0) - n
                if left > 0:
                    table[requester] = left
                else:
                    table.pop(requester, None)
        if self.sharing is not sharing:
            # reloaded while this one started (`end_unshared` did not see it): the new
            # policy decides whether it runs
            await self._recheck(record, requester)
        self._exports[record.id] = record
        if creating is not None:
            self._by_conversation[creating] = record.id
        log.info("%s: export %s of %s to %s", self, record.id, record.labels, receivers)
        if cancelled:  # its requester stopped waiting for this answer
            await self._end(record)
        return {"id": record.id, "labels": record.labels, "to-units": receivers}

    def _check_limits(self, requester: str, needed: int, history: int) -> None:
        """The export limits, global and per requesting platform; Denied names the one hit."""
        active = self.export_count + self._reserved
        if active + needed > self.max_exports:
            raise Denied(
                "export-limit",
                f"too many exports (limit {self.max_exports}: {active} running, {needed} asked)",
            )
        if requester == self.platform.name:
            return  # this platform's own agents share only the global pool
        mine = [r for r in self._exports.values() if platform_of(r.requester) == requester]
        limit = self.max_exports_per_platform
        if limit is not None:
            held = sum(len(r.handles) for r in mine) + self._reserved_by.get(requester, 0)
            if held + needed > limit:
                raise Denied(
                    "export-limit",
                    f"too many exports for {requester} (export_limit_per_platform {limit}: "
                    f"{held} running, {needed} asked)",
                )
        hlimit = self.max_history_per_platform
        if hlimit is not None and history:
            kept = sum(r.history * len(r.handles) for r in mine)
            kept += self._history_reserved_by.get(requester, 0)
            if kept + history * needed > hlimit:
                raise Denied(
                    "history-limit",
                    f"too much history for {requester} (history_limit_per_platform {hlimit} "
                    f"samples: {kept} kept, {history * needed} asked)",
                )

    async def _start_export(
        self,
        exporter: Exporter,
        local: str,
        semantic: str,
        receiver: str,
        policy: Policy,
        requester: str,
        history: int,
    ) -> Any:
        start = exporter.start_exporting
        try:
            return await _resolved(start(local, semantic, receiver, policy, history=history))
        except UnknownLabelError:
            # An object this platform has not anchored yet (the paper's car5): the
            # application may anchor it now and create its stream; then export it.
            if self.anchor is None or self.instance.has_label(local):
                raise
            if not await self.anchor(semantic, local, requester):
                raise
            return await _resolved(start(local, semantic, receiver, policy, history=history))

    async def _cancel_stream(self, export_id: str, sender: str) -> dict[str, Any]:
        record = self._exports.get(export_id)
        if record is None:
            raise ContentError(f"no export {export_id!r} here")
        who = platform_of(sender)
        allowed = {platform_of(record.requester), self.platform.name, *record.receivers}
        if who not in allowed:
            raise ContentError(
                f"{sender} may not cancel export {export_id}: it neither asked for it nor gets it"
            )
        await self._end(record)
        return {"cancelled": export_id}

    def _is_export_cancel(self, message: ACLMessage) -> bool:
        """A cancel of an export's conversation, or one that may be of a create-stream
        not taken up yet (an initiator's: in a conversation, in reply to nothing)."""
        key = (message.sender, message.conversation_id or "")
        if key in self._by_conversation or key in self._creating:
            return True
        return message.conversation_id is not None and message.in_reply_to is None

    async def _on_cancel(self, message: ACLMessage) -> None:
        """FIPA cancel of a create-stream by its requester: stop the export, confirm.

        One still being created is stopped as soon as it started (its requester gave up);
        one whose create-stream was not taken up yet, as soon as it is (bounded: the
        latest `_MAX_CANCELLED_EARLY` such cancels are kept, at most
        `_MAX_CANCELLED_EARLY_BY_SENDER` of one sender's).
        """
        key = (message.sender, message.conversation_id or "")
        if key in self._creating:
            self._creating[key] = True
        elif key not in self._by_conversation and message.conversation_id is not None:
            early = self._cancelled_early
            early[key] = None
            # a cancel message is rare: a scan of the (bounded) kept ones costs little
            mine = [kept for kept in early if kept[0] == message.sender]
            if len(mine) > _MAX_CANCELLED_EARLY_BY_SENDER:
                del early[mine[0]]
            while len(early) > _MAX_CANCELLED_EARLY:
                del early[next(iter(early))]
        export_id = self._by_conversation.get(key)
        record = self._exports.get(export_id or "")
        if record is not None:
            await self._end(record)
        await self.reply(message, P.INFORM, {"cancelled": export_id})

    async def _end(self, record: StreamExport) -> None:
        self._exports.pop(record.id, None)
        if record.conversation_id is not None:
            self._by_conversation.pop((record.requester, record.conversation_id), None)
        await self._stop_handles(record)
        log.info("%s: export %s stopped", self, record.id)

    async def _stop_handles(
        self, record: StreamExport, receiver: str | None = None, *, why: str | None = None
    ) -> None:
        exporter = self.exporter
        for key, handle in list(record.handles.items()):
            if receiver is not None and key[1] != receiver:
                continue
            del record.handles[key]
            if exporter is None:
                continue
            try:
                await _resolved(exporter.stop(handle, why=why))
            except Exception:
                log.exception("%s: stopping the export of %r to %s", self, *key)

    async def end_unshared(self, why: str) -> list[tuple[str, str, str, str]]:
        """End the exports ``sharing`` no longer allows (a policy reloaded): what ended.

        Each export of a label to a receiver is checked as a create-stream of it is now
        (its requester and its receiver may stream it); one refused stops, its receiver
        told `UNSHARED_WHY` (its import ends there, as when an export ends by itself),
        ``why`` and the refusal logged here. Returns (export id, label, receiver,
        refusal) of each one ended.
        """
        check = self._refusal
        return await self._end_exports(
            lambda semantic, requester, receiver: (
                check(semantic, requester) or check(semantic, receiver)
            )
        )

    async def end_revoked(self, platform: str) -> list[tuple[str, str, str, str]]:
        """End what ``platform``, removed from the trust file, holds here: the exports to it
        or asked for by it, its membership subscriptions, its streams to ask for again.

        It is told nothing (nothing is sealed for it any more); another receiver of an
        export it asked for is told `UNSHARED_WHY`. Returns (export id, label, receiver,
        reason) of each export ended.
        """
        reason = f"platform {platform!r} was removed from the trust file (revoked)"
        subscribers = self._subscribers.subscribers
        for key in [k for k in subscribers if platform_of(k[0]) == platform]:
            del subscribers[key]
        self._durable.pop(platform, None)
        ended = await self._end_exports(
            lambda semantic, requester, receiver: (
                reason if platform in (requester, receiver) else None
            ),
            tell=lambda receiver: receiver != platform,
        )
        for record in self._exports.values():
            record.receivers = [w for w in record.receivers if w != platform]
        return ended

    async def _end_exports(
        self,
        refusal: Callable[[str, str, str], str | None],
        tell: Callable[[str], bool] = lambda receiver: True,
    ) -> list[tuple[str, str, str, str]]:
        """End each export of a label to a receiver ``refusal(label, requester platform,
        receiver)`` names a reason for; its receiver told `UNSHARED_WHY` if ``tell`` it."""
        exporter = self.exporter
        self._prune_ended()
        ended: list[tuple[str, str, str, str]] = []
        stops: list[tuple[tuple[str, str], Any]] = []
        touched: list[StreamExport] = []
        for record in list(self._exports.values()):
            requester = platform_of(record.requester)
            for key, handle in list(record.handles.items()):
                semantic, receiver = key
                reason = refusal(semantic, requester, receiver)
                if reason is None:
                    continue
                del record.handles[key]
                ended.append((record.id, semantic, receiver, reason))
                log.warning("%s: export %s of %r to %s ended: %s", self, record.id, *key, reason)
                stops.append((key, handle))
                if record not in touched:
                    touched.append(record)
        if exporter is not None and stops:
            # every one refused is out of its record (no agreement left) before any is
            # stopped; the stops run together: each export ends at once (it sends no more)
            # and then tells its receiver, the fact only (the rule's platform list and the
            # config's path stay here, in the log and audit, and the marker stays small)
            results = await asyncio.gather(
                *(
                    _resolved(exporter.stop(h, why=UNSHARED_WHY if tell(key[1]) else None))
                    for key, h in stops
                ),
                return_exceptions=True,
            )
            for (key, _), result in zip(stops, results, strict=True):
                if isinstance(result, Exception):
                    log.error(
                        "%s: stopping the export of %r to %s",
                        self,
                        *key,
                        exc_info=result,
                    )
        for record in touched:
            if not record.handles:
                await self._end(record)
        return ended

    async def _recheck(self, record: StreamExport, requester: str) -> None:
        """Denied (the export stopped) if the policy in force refuses any of ``record``."""
        for semantic in record.labels:
            for who in (requester, *record.receivers):
                reason = self._refusal(semantic, who)
                if reason is not None:
                    await self._stop_handles(record, why=UNSHARED_WHY)  # receivers told
                    raise Denied("sharing-rule", reason)

    def _refusal(self, semantic: str, platform: str) -> str | None:
        """Why ``platform`` may not stream ``semantic`` now (None: it may, or it is us)."""
        if platform == self.platform.name:
            return None
        return self.sharing.check("stream", semantic, platform)

    async def _stop_exports_to(self, platform: str) -> None:
        for record in list(self._exports.values()):
            if platform not in record.receivers:
                continue
            await self._stop_handles(record, platform)
            record.receivers = [w for w in record.receivers if w != platform]
            if not record.handles:
                await self._end(record)
            log.info("%s: %s is gone; export %s to it stopped", self, platform, record.id)

    # -- queries and search ---------------------------------------------------------------

    def _query(self, req: Query, sender: str) -> dict[str, Any]:
        asker = platform_of(sender)
        if req.to_units is not None and any(u != asker for u in req.to_units):
            raise ContentError(
                "the answer to a query goes to the asker: 'to-units' may only name its platform"
            )
        if isinstance(req, GetLatest):
            return self._latest(req.labels, asker)
        labels = list(dict.fromkeys(req.labels))
        return self._answers(req, labels, self._locals(labels, asker))

    def _locals(self, labels: list[str], asker: str) -> list[str]:
        """The local labels of ``labels`` if ``asker``'s platform may query them all."""
        if asker != self.platform.name:  # `_check_sharing` of each label
            reason = self.sharing.check_all("query", labels, asker)
            if reason is not None:
                raise Denied("sharing-rule", reason)
        # `_translate` of each label, without its calls (a try in the loop costs nothing)
        to_local = self.translator.to_local
        out: list[str] = []
        for semantic in labels:
            try:
                out.append(to_local(semantic))
            except Exception as exc:
                raise ContentError(_about(semantic, _reason(exc))) from exc
        return out

    def _latest(self, labels: list[str], asker: str) -> dict[str, Any]:
        """The answer to a get-latest of ``labels`` (checked content) from ``asker``'s platform."""
        return self._latest_reply(labels, asker, hand_over=False)

    def _latest_reply(self, labels: list[str], asker: str, *, hand_over: bool = True) -> Any:
        """`_latest`, handed over to its reply (`HandedOver`) when it is plain JSON.

        The answer's dicts and lists are made here and kept nowhere else; with labels and
        values of exact JSON types, the reply needs no copy or check of it.
        """
        key = tuple(labels)
        by = self._resolved_by
        translator = self.translator
        resolved = None
        if (
            by is not None
            and by[0] is translator
            and by[1] is by[0].mapping
            and by[2] is by[1].vocabulary
        ):
            resolved = self._resolved.get(key)
        if resolved is None:
            labels = list(dict.fromkeys(labels))
            local = self._locals(labels, asker)
            only_str = _only_str(map(type, labels))
            self._remember(key, labels, local, only_str)
        else:
            labels, local, only_str = resolved
            if asker != self.platform.name:  # `_locals`' sharing check, every time
                reason = self.sharing.check_all("query", labels, asker)
                if reason is not None:
                    raise Denied("sharing-rule", reason)
        try:
            contents, plain = latest_contents_plain(self.instance, local)
        except Exception:  # `_answers` raises it again, named per label
            return self._answers(None, labels, local)
        answer = dict(zip(labels, contents, strict=True))
        if hand_over and plain and only_str:
            return HandedOver(answer)
        return answer

    def _remember(
        self, key: tuple[Any, ...], labels: list[str], local: list[str], only_str: bool
    ) -> None:
        """Keep the translation of a get-latest's labels, if the translator's may be kept.

        Only a `PlatformLabels` (not a subclass) answers from its mapping alone, and a
        `LabelMapping` and its `Vocabulary` are never changed once made: the translation
        holds while the three are the same objects. Another translator may answer
        otherwise each time: nothing is kept for it. At most `_MAX_RESOLVED` labels are
        kept (then all are dropped, and kept again as they are asked).
        """
        translator = self.translator
        if type(translator) is not PlatformLabels:
            return
        mapping = translator.mapping
        if type(mapping) is not LabelMapping or type(mapping.vocabulary) is not Vocabulary:
            return
        by = self._resolved_by
        resolved = self._resolved
        if (
            by is None
            or by[0] is not translator
            or by[1] is not mapping
            or by[2] is not mapping.vocabulary
            or self._resolved_labels + len(key) > _MAX_RESOLVED
        ):
            # a new dict, not cleared: `answer_on_thread` may be reading the old one
            self._resolved = resolved = {}
            self._resolved_labels = 0
            self._resolved_by = by = (translator, mapping, mapping.vocabulary)
            self._resolved_view = (by, resolved)
        if len(key) <= _MAX_RESOLVED:
            # its lists are never changed once kept (another thread may read them)
            resolved[key] = (labels, local, only_str)
            self._resolved_labels += len(key)

    def _answers(
        self, req: GetValueAt | GetTrajectory | None, labels: list[str], local_labels: list[str]
    ) -> dict[str, Any]:
        """Each label's answer to ``req`` (None: get-latest), or the refusal naming the label."""
        out: dict[str, Any] = {}
        # get-latest: the gateway's "latest" query, without building its model per label
        latest = self.instance.latest
        for semantic, local in zip(labels, local_labels, strict=True):
            try:
                if req is None:
                    answer = latest(local)
                else:
                    answer = self.gateway.query(_gateway_query(req, local))
            except UnknownLabelError as exc:
                # The core's message lists local labels: it must not leave the platform.
                raise ContentError(f"label {semantic!r}: no stream for it here") from exc
            except GatewayRefusal as exc:
                raise ContentError(exc.reason.replace(local, semantic)) from exc
            except (DyKnowError, OverflowError) as exc:
                raise ContentError(_about(semantic, str(exc).replace(local, semantic))) from exc
            out[semantic] = answer_content(answer)  # without the local label
        return out

    def _search(self, formula: str) -> dict[str, Any]:
        search = self.label_search
        if search is None:
            raise ContentError("this platform has no label search")
        try:
            found = search.find(formula)
        except Exception as exc:
            raise ContentError(_reason(exc)) from exc
        return {"labels": list(dict.fromkeys(found))}

    # -- asking others ------------------------------------------------------------------

    def provider_of(self, platform: str) -> str:
        """The federation agent of ``platform`` (from the global directory, else the default)."""
        if platform == self.platform.name:
            return self.aid
        gdf = self.platform.global_df
        if gdf is not None:
            for s in gdf.services(platform):
                if s.type == FEDERATION_SERVICE_TYPE:
                    return s.provider
        return agent_id(FEDERATION_AGENT, platform)

    async def request_from(
        self,
        platform: str,
        content: Any,
        *,
        timeout: float = DEFAULT_TIMEOUT,
        conversation_id: str | None = None,
    ) -> Any:
        """FIPA-Request to the federation service of ``platform``: the inform's content."""
        return await request(
            self,
            self.provider_of(platform),
            content,
            ontology=ONTOLOGY,
            timeout=timeout,
            conversation_id=conversation_id,
        )

    async def create_stream(
        self,
        provider: str,
        labels: Iterable[str],
        *,
        to_units: Iterable[str] | None = None,
        sample_period: float | None = None,
        max_delay: float | None = None,
        start: float | None = None,
        end: float | None = None,
        relative: bool = False,
        history: int = 0,
        durable: bool = False,
        timeout: float = DEFAULT_TIMEOUT,
    ) -> str:
        """Ask platform ``provider`` to export ``labels`` (to us by default); the export id.

        ``history`` N asks the exporter to keep its last N samples and resend those a
        partition made us miss. ``durable`` asks again by itself whenever ``provider``
        comes back after it was gone (a restart, a router restart, a long partition):
        exports to a platform gone are stopped at the provider. Given up (no answer
        within ``timeout``, or cancelled), the provider is sent a FIPA ``cancel`` so an
        export it started does not run until its lease.
        """
        content: dict[str, Any] = {"action": "create-stream", "labels": list(labels)}
        for key, value in (
            ("to-units", None if to_units is None else list(to_units)),
            ("sample-period", sample_period),
            ("max-delay", max_delay),
            ("from", start),
            ("to", end),
        ):
            if value is not None:
                content[key] = value
        if relative:
            content["relative"] = True
        if history:
            content["history"] = history
        held = self._expect_from(provider, content)
        others = [
            (provider, w, s)
            for w in dict.fromkeys(content.get("to-units", []))
            if w != self.platform.name
            for s in dict.fromkeys(content["labels"])
        ]
        self._count_for_others(others, +1)  # the receivers ask us to confirm it meanwhile
        conversation = new_id("c")
        try:
            answer = await self.request_from(
                provider, content, timeout=timeout, conversation_id=conversation
            )
            export_id = str(answer["id"])
        except BaseException as exc:
            # refused, failed, timed out, unreachable or cancelled: nothing stays agreed
            self._count_for_others(others, -1)
            gave_up = isinstance(exc, ReplyTimeout | asyncio.CancelledError)
            self._settle(held, accepted=False, gave_up=gave_up)
            if gave_up:
                # the provider may have started it: nothing agreed covers it any more
                self._give_up(provider, conversation)
            raise
        self._settle(held, accepted=True)
        if others:
            self._for_others_by[(provider, export_id)] = others
        if durable:
            self._durable.setdefault(provider, {})[export_id] = _Durable(content, export_id)
        return export_id

    def _give_up(self, provider: str, conversation_id: str) -> None:
        """Tell ``provider`` (FIPA cancel in the create-stream's conversation) we gave up.

        Best-effort and in the background: once the provider handles the create-stream,
        the cancel stops its export (at once, or as soon as it started); one that arrives
        before is kept there and stops it as soon as it starts; one lost on the way leaves
        the export to end with its lease (we withdrew the stream, so nothing here renews it).
        """
        cancel = self.message(
            P.CANCEL,
            self.provider_of(provider),
            None,
            protocol=FIPA_REQUEST,
            ontology=ONTOLOGY,
            conversation_id=conversation_id,
        )
        try:
            self.spawn(self._send_quietly(cancel), "give-up")
        except Exception as exc:  # stopping: the export ends with its lease there
            log.info("%s: not cancelling the create-stream at %s: %s", self, provider, exc)

    async def _send_quietly(self, message: ACLMessage) -> None:
        """Send ``message``; a failure is logged (what it asks ends by a lease anyway)."""
        try:
            await self.send(message)
        except Exception as exc:
            what = message.performative
            log.info("%s: %s to %s not sent: %s", self, what, message.receivers, exc)

    def _count_for_others(self, keys: list[tuple[str, str, str]], delta: int) -> None:
        table = self._for_others
        for key in keys:
            n = table.get(key, 0) + delta
            if n > 0:
                table[key] = n
            else:
                table.pop(key, None)

    def _expect_from(self, provider: str, content: Any) -> list[_Held]:
        """Agree to receive what a create-stream ``content`` asks ``provider`` to send us.

        Before asking: the first batch may overtake the provider's inform. Agreed
        tentatively: the (provider, label, counted) entries returned, to `_settle` once
        answered (counted: in ``_tentative`` for this request; not counted: agreed before,
        made ours for good if the provider accepts). Accepted, it stays agreed after a
        cancel: the same stream asked again (a new policy) lands in the same label and its
        subscribers go on.
        """
        imports = self.imports
        if imports is None or provider == self.platform.name:
            return []
        if not isinstance(content, dict) or content.get("action") != "create-stream":
            return []
        units = content.get("to-units")
        if units is not None and self.platform.name not in units:
            return []  # for others only: they agree themselves when the provider asks them
        labels = content.get("labels", content.get("semantic-labels"))
        tentative = self._tentative
        held: list[_Held] = []
        try:
            for semantic in dict.fromkeys(labels if isinstance(labels, list) else []):
                if not isinstance(semantic, str):
                    continue
                key = (provider, semantic)
                if key in tentative:
                    tentative[key] += 1  # another request of ours, not answered yet
                elif imports.agreed(provider, semantic):
                    # agreed before (accepted, consented, by the application): kept as it
                    # is if we are refused; a consent's lease ends if we are accepted
                    held.append((provider, semantic, False))
                    continue
                else:
                    imports.expect(provider, semantic)
                    tentative[key] = 1
                held.append((provider, semantic, True))
        except BaseException:
            self._settle(held, accepted=False)  # a label that cannot land: none stays
            raise
        return held

    def _settle(self, held: list[_Held], *, accepted: bool, gave_up: bool = False) -> None:
        """A request that expected ``held`` was answered: keep them, or withdraw them.

        Accepted, they are agreed for good. Otherwise each is withdrawn once no other
        request of ours still waits for it, unless one was accepted meanwhile; one whose
        samples already landed here ends then (the provider stopped what it started, or
        our cancel stops it, and no end marker follows either).
        """
        tentative = self._tentative
        for provider, semantic, counted in held:
            key = (provider, semantic)
            if accepted:
                # for good: a consent's lease on it (taken before or meanwhile) ends
                tentative.pop(key, None)
                self._keep(provider, semantic)
                continue
            n = tentative.get(key)
            if not counted or n is None:
                continue  # agreed before, or another request for it was accepted
            if n > 1:
                tentative[key] = n - 1
            else:
                del tentative[key]
                self._withdraw(provider, semantic, gave_up=gave_up)

    def keep_import(self, provider: str, semantic: str) -> None:
        """``provider``'s ``semantic`` is agreed for good: a request of ours that fails keeps it."""
        self._tentative.pop((provider, semantic), None)

    def _keep(self, provider: str, semantic: str) -> None:
        """Our request for it was accepted: agreed for good (a consent's lease ends)."""
        imports = self.imports
        if imports is None:
            return
        try:
            imports.expect(provider, semantic)
        except Exception:  # the provider accepted: what we asked for is not undone
            log.exception("%s: agreeing to %s from %s failed", self, semantic, provider)

    def _withdraw(self, provider: str, semantic: str, *, gave_up: bool = False) -> None:
        """Undo our agreement to receive ``provider``'s ``semantic`` (a request failed)."""
        imports = self.imports
        if imports is None:
            return
        try:
            if gave_up:  # asked only then: agreements written before it keep working
                imports.withdraw(provider, semantic, gave_up=True)
            else:
                imports.withdraw(provider, semantic)
        except Exception:  # a failed request's cleanup: what failed is already raised
            log.exception("%s: withdrawing %s from %s failed", self, semantic, provider)

    async def cancel_stream(
        self, provider: str, export_id: str, *, timeout: float = DEFAULT_TIMEOUT
    ) -> None:
        """Ask platform ``provider`` to stop export ``export_id`` (the id create_stream gave)."""
        entry = self._durable.get(provider, {}).pop(export_id, None)
        current = export_id if entry is None else entry.current  # created again since?
        self._count_for_others(self._for_others_by.pop((provider, export_id), []), -1)
        await self.request_from(
            provider, {"action": "cancel-stream", "id": current}, timeout=timeout
        )

    def providers(self, *, include_self: bool = False) -> dict[str, str]:
        """Platform → federation agent, for every member in the global directory."""
        gdf = self.platform.global_df
        if gdf is None:
            raise ServiceError(f"platform {self.platform.name} keeps no global directory")
        # Computed again only when the directory changed: walking every member's services
        # cost ~70 µs of each global request (measured with 32 members)
        cached = self._providers.get(include_self)
        if cached is not None and cached[0] is gdf and cached[1] == gdf.version:
            return cached[2].copy()
        version = gdf.version
        found: dict[str, str] = {}
        me = self.platform.name
        # gdf.search(type=…), without validating a query each time: this runs per global
        # request, over every member's services
        for s in gdf.services():
            if s.type == FEDERATION_SERVICE_TYPE:
                platform = platform_of(s.provider)
                if platform != me:
                    found.setdefault(platform, s.provider)
        if include_self:
            found[self.platform.name] = self.aid
        found = dict(sorted(found.items()))
        self._providers[include_self] = (gdf, version, found)
        return found.copy()

    def _unlisted(self) -> list[str]:
        """The members a global request leaves out: the directory does not list them yet."""
        # A member's signed events made it one, but its entries are held aside until its
        # signed snapshot is read (a loaded machine: seconds); said, not silently left out.
        # Only those: a member merely without a provider is not waiting to be listed
        gdf = self.platform.global_df
        if gdf is None:
            return []
        return [p for p in gdf.unconfirmed if p in self._members]

    async def global_request(
        self,
        content: Any,
        *,
        deadline: float,
        select: Select = "first",
        include_self: bool = False,
    ) -> GlobalResult:
        """Ask every member's federation service at once; answers until ``deadline`` s.

        A reading action (``get-*``, ``search-labels``, ``list-labels``) is asked as
        query-ref, any other as request. Returns as soon as everyone answered, else at
        the deadline. A member the directory does not list (yet) is not asked: it is
        named in ``unlisted``. ``select``: the
        ``"first"`` answer to arrive, the ``"newest"`` by valid time (its newest sample),
        or a function fusing ``{platform: answer}`` (may be async). Do not call it from a
        handler of this agent with ``include_self``: our own request would wait behind it.
        """
        if deadline <= 0:
            raise ValueError(f"deadline must be positive, got {deadline}")
        if select not in ("first", "newest") and not callable(select):
            raise ValueError(f"select must be 'first', 'newest' or a function, not {select!r}")
        providers = self.providers(include_self=include_self)
        result = GlobalResult(asked=list(providers), unlisted=self._unlisted())
        if not providers:
            return result
        held: dict[str, list[_Held]] = {}
        if isinstance(content, dict) and content.get("action") == "create-stream":
            try:
                for platform in providers:
                    # a global create-stream: to us, agreed until that provider refuses
                    held[platform] = self._expect_from(platform, content)
            except BaseException:
                for keys in held.values():
                    self._settle(keys, accepted=False)
                raise
        conversation_id = new_id("c")
        creates = isinstance(content, dict) and content.get("action") == "create-stream"
        try:
            result = await self._global_request(
                content, providers, result, deadline, conversation_id
            )
        except BaseException:
            for keys in held.values():
                self._settle(keys, accepted=False, gave_up=creates)
            if creates:  # given up on all of them: an export one started is stopped
                for platform in providers:
                    self._give_up(platform, conversation_id)
            raise
        for platform, keys in held.items():
            gave_up = platform in result.no_answer
            self._settle(keys, accepted=platform in result.answers, gave_up=gave_up)
        if creates:
            for platform in result.no_answer:  # silent until the deadline: given up
                self._give_up(platform, conversation_id)
        await _select(result, select)
        return result

    async def _global_request(
        self,
        content: Any,
        providers: dict[str, str],
        result: GlobalResult,
        deadline: float,
        conversation_id: str,
    ) -> GlobalResult:
        """Send ``content`` to every provider; ``result`` with the answers until ``deadline``."""
        # A reading action goes as query-ref: each provider answers it in its agent's receive
        # loop, not in a task of its own per request as an action (which may wait) needs.
        if isinstance(content, dict) and content.get("action") in _READS:
            performative, protocol = P.QUERY_REF, FIPA_QUERY
        else:
            performative, protocol = P.REQUEST, FIPA_REQUEST
        loop = asyncio.get_running_loop()
        end = loop.time() + deadline
        pending = set(providers)
        # One message checked (its content copied) once; each provider's is a copy of it
        # with its own receiver (a directory entry's provider) and reply_with (readdressed)
        first = self.message(
            performative,
            next(iter(providers.values())),
            content,
            protocol=protocol,
            ontology=ONTOLOGY,
            language="json",
            conversation_id=conversation_id,
            reply_with=new_id("r"),
            reply_by=time.time() + deadline,
        )
        me = self.platform.name
        sends_now = getattr(self.platform.channel, "sends_now", None)
        with self.conversation(conversation_id, peers=providers.values()) as conv:
            sends: dict[str, asyncio.Task[None]] = {}
            for i, (platform, aid) in enumerate(providers.items()):
                message = first if i == 0 else first.readdressed(aid, new_id("r"))
                if platform == me or (sends_now is not None and sends_now(platform)):
                    # Nothing to wait for but the transport: sent in turn, without a task
                    try:
                        await conv.send(message)
                    except Exception as error:
                        result.refused[platform] = f"unreachable: {reason_of(error)}"
                        pending.discard(platform)
                    continue
                # Concurrently: a platform slow to reach (a key exchange) holds up no other.
                sends[platform] = loop.create_task(
                    conv.send(message), name=f"global-request[{conversation_id}].send[{platform}]"
                )
            if sends:
                try:
                    await asyncio.wait(sends.values(), timeout=deadline)
                finally:
                    for task in sends.values():
                        task.cancel()  # no-op for those done; none outlives this call
                    await asyncio.wait(sends.values())
            for platform, task in sends.items():
                if task.cancelled():
                    reason = "unreachable: sending did not finish before the deadline"
                elif (exc := task.exception()) is not None:
                    reason = f"unreachable: {reason_of(exc)}"
                else:
                    continue
                result.refused[platform] = reason
                pending.discard(platform)
            # Woken once, when every answer is in (or at the deadline), not once per answer
            await conv.gather([providers[p] for p in pending], deadline=end)
            # What came (everything, unless the deadline came first) is read at once; then,
            # while some have not answered, what comes until the deadline
            came = iter(conv.drain())
            while pending:
                m = next(came, None)
                if m is None:
                    try:
                        m = await conv.receive(deadline=end)
                    except ReplyTimeout:
                        break
                platform = platform_of(m.sender)
                if platform not in pending or m.performative is P.AGREE:
                    continue
                pending.discard(platform)
                if m.performative in (P.INFORM, P.INFORM_REF):
                    result.answers[platform] = m.content
                else:
                    content_text = m.content if isinstance(m.content, str) else str(m.content)
                    result.refused[platform] = f"{m.performative}: {content_text}"
        result.no_answer = [p for p in providers if p in pending]
        return result

    async def _global_on_behalf(self, req: GlobalRequest, message: ACLMessage) -> Any:
        if platform_of(message.sender) != self.platform.name:
            raise ContentError("global requests are made for agents of this platform only")
        if req.request.get("action") == "global-request":
            raise ContentError("a global request cannot ask for another global request")
        result = await self.global_request(
            req.request, deadline=req.deadline, select=req.select, include_self=req.include_self
        )
        return result.to_content()


_READS = QUERY_ACTIONS | {"list-labels"}


def _take(buckets: dict[str, TokenBucket], platform: str) -> bool:
    """Take a token of ``platform``'s accept/consent budget (made on first use)."""
    now = time.monotonic()
    bucket = buckets.get(platform)
    if bucket is None:
        bucket = buckets[platform] = TokenBucket(ACCEPT_RATE, ACCEPT_BURST, now)
    return bucket.take(now)


async def _select(result: GlobalResult, select: Select) -> None:
    answers = result.answers
    if not answers:
        return
    if select == "first":
        result.chosen = next(iter(answers))
    elif select == "newest":
        order = list(answers)

        def key(platform: str) -> tuple[bool, float, int]:
            tv = newest_valid_time(answers[platform])
            # Answers with a sample beat those without; ties go to the earlier answer.
            return (tv is not None, tv if tv is not None else 0.0, -order.index(platform))

        result.chosen = max(order, key=key)
    else:
        fuse: Callable[[dict[str, JsonValue]], Any | Awaitable[Any]] = select
        result.value = await _resolved(fuse(dict(answers)))
        return
    result.value = answers[result.chosen]


def _gateway_query(req: Query, local: str) -> GatewayQuery:
    """The gateway's query for one local label."""
    data: dict[str, Any] = {"action": "query", "label": local, "relative": req.relative}
    if isinstance(req, GetLatest):
        data["kind"] = "latest"
    elif isinstance(req, GetValueAt):
        data.update(kind="at", t=req.t, approximation=req.approximation)
    else:
        data["kind"] = "between"
        if req.start is not None:
            data["from"] = req.start
        if req.end is not None:
            data["to"] = req.end
    query: GatewayQuery = GatewayQuery.model_validate(data)
    return query
