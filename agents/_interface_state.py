"""The Interface Agent's state: what __init__ makes, which every part of it reads."""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ._acl import MAX_MESSAGE_BYTES, ACLMessage
from ._agent import Agent
from ._audit import AuditLog
from ._bucket import TokenBucket
from ._exceptions import AuthenticationError, MessageError
from ._interface_common import (
    _AUDIT_HELD,
    DEFAULT_RATE_LIMIT,
    WATCH_RATE,
    RateLimit,
    _burst_of,
    _Sender,
)
from ._kxgate import DEFAULT_KX_LIMIT, KxGate, KxLimit
from ._security import (
    Clock,
    Handshake,
    KeyPair,
    SecurityPolicy,
    SessionTable,
    TrustStore,
    WatchGate,
)
from .transports import Handle, Inbox, Presence, Subscription

if TYPE_CHECKING:
    from ._platform import AgentPlatform


class _InterfaceState:
    """The Interface Agent's settings and state, made here and shared by its parts."""

    def __init__(
        self,
        keys: KeyPair,
        trust: TrustStore,
        *,
        policy: SecurityPolicy | None = None,
        audit_path: str | Path | None = None,
        audit_max_bytes: int = AuditLog.DEFAULT_MAX_BYTES,
        audit_backups: int = AuditLog.DEFAULT_BACKUPS,
        publish_audit: bool = True,
        seal_audit: bool = True,
        watchable: bool = True,
        watch_lease: float = 10.0,
        audit_interval: float = 0.25,
        handshake_timeout: float = 2.0,
        rehandshake_interval: float = 5.0,
        max_bytes: int = MAX_MESSAGE_BYTES,
        clock: Clock = time.time,
        rate_limit: RateLimit | None = DEFAULT_RATE_LIMIT,
        monotonic: Callable[[], float] = time.monotonic,
        kx_limit: KxLimit | None = DEFAULT_KX_LIMIT,
        batch: bool = True,
        lane: bool = True,
        binary_acl: bool = True,
        lane_replies: bool = True,
    ) -> None:
        self.keys = keys
        self.trust = trust
        self.policy = policy or SecurityPolicy()
        self.audit = AuditLog(
            path=audit_path,
            platform=keys.platform,
            max_bytes=audit_max_bytes,
            backups=audit_backups,
        )
        self.audit.wake = self._wake_flush
        # the audit flush sleeps while it has nothing to do (`_flush_audit`); any thread wakes it
        self._flush_idle = False
        self._flush_due = asyncio.Event()
        self._flush_loop: asyncio.AbstractEventLoop | None = None
        self.publish_audit = publish_audit
        self.seal_audit = seal_audit
        # Audit batches nobody could receive are not sealed nor published, but kept for
        # `AUDIT_HOLD` s (at most `_AUDIT_HELD` of them): a watcher that came meanwhile
        # (the transport tells of it late) gets them with the next batch published
        self._audit_held: deque[tuple[float, bytes]] = deque(maxlen=_AUDIT_HELD)
        self.audit_published = 0  # audit batches sealed and published, since start
        self.audit_unheard = 0  # audit batches not published: no subscriber, since start
        self.watchable = watchable
        self.watch_lease = watch_lease
        # what the owner watches: (kind, peer, time, body) while a lease runs; bounded, as
        # nothing drains it faster than the flush interval (an overflow loses the oldest)
        self.mirroring = False
        self._mirror: deque[tuple[str, str, float, bytes]] = deque(maxlen=16_384)
        self._mirror_until = -math.inf
        self._watch_handle: Handle | None = None
        self._watch_gate = WatchGate(keys, trust.federation, policy=self.policy, clock=clock)
        self._owner_clock = clock  # the time signed into the batches for the owner
        # watch requests are screened on the transport's thread, as key exchanges are: a
        # flood of them would cost the event loop a task each (the owner asks once a lease)
        self._watch_lock = threading.Lock()
        self._watch_bucket = TokenBucket(WATCH_RATE, WATCH_RATE, monotonic())
        self.watch_shed = 0  # watch requests dropped before the event loop, since start
        self.watch_refused = 0  # watch requests let through whose check refused them
        self._watch_shed_pending = 0  # since the last audit record
        self.audit_interval = audit_interval
        self.handshake_timeout = handshake_timeout
        self.rehandshake_interval = rehandshake_interval
        self.max_bytes = max_bytes
        self.handshake = Handshake(keys, trust, policy=self.policy, clock=clock)
        self.sessions = SessionTable(keys.platform, trust, policy=self.policy, clock=clock)
        self.binary_acl = binary_acl
        # how every ACL envelope is sealed (the form a receiver tells by its first byte);
        # chosen again at start, as batching is
        self._seal = self.sessions.seal_binary if binary_acl else self.sessions.seal
        self._handshakes: dict[str, asyncio.Future[None]] = {}
        # the key exchange under way with each peer, ended at once by its signed leave
        # per peer, the key exchange under way with it and when it began (clock s)
        self._exchanging: dict[str, tuple[asyncio.Timeout, float]] = {}
        self._clock = clock
        self._last_rehandshake: dict[str, float] = {}
        # Liveliness is not authenticated: per trusted peer, the presence changes acted on
        # (`_presence_admits`), when one last lifted its re-handshake limiter, the changes
        # ignored since the last audit record, and the doubt that stands in for them later
        self._presence_buckets: dict[str, TokenBucket] = {}
        self._presence_lifted: dict[str, float] = {}
        self._presence_ignored: dict[str, int] = {}
        self._presence_last_report = -math.inf
        self._presence_later: dict[str, asyncio.TimerHandle] = {}
        self._subs: list[Subscription[Any]] = []
        self._kx: Handle | None = None
        self._host: AgentPlatform | None = None
        self.agent: Agent | None = None
        if rate_limit is not None and not isinstance(rate_limit, RateLimit):
            raise TypeError(f"rate_limit: expected a RateLimit or None, got {rate_limit!r}")
        self.rate_limit = rate_limit
        self._monotonic = monotonic
        self._senders: dict[str, _Sender] = {}
        # envelopes that do not open: their audit records share one budget (any source)
        self._unauth = (
            TokenBucket(rate_limit.unauthenticated, _burst_of(rate_limit.unauthenticated), 0.0)
            if rate_limit is not None
            else None
        )
        self._unauth_pending = 0
        self._unauth_last_report = -math.inf
        self._untrusted_logged: set[str] = set()  # names logged in the current interval
        self._untrusted_unlogged = 0  # refusals of other names since, summed up next
        self._untrusted_since = -math.inf
        if kx_limit is not None and not isinstance(kx_limit, KxLimit):
            raise TypeError(f"kx_limit: expected a KxLimit or None, got {kx_limit!r}")
        # key-exchange requests are screened on the transport's thread (see _kxgate)
        self.kx_gate = (
            KxGate(self.handshake, kx_limit, monotonic=monotonic, on_shed=self._count_shed)
            if kx_limit is not None
            else None
        )
        self._alive: set[str] = set()
        self.reply_to_refused = 0  # requests whose reply_to named a third platform
        self.batch = batch
        self._batching = False  # batch, and the transport can publish from a loop callback
        # per platform: the messages waiting for the end of this turn of the loop (the
        # entry exists while a flush is scheduled: a message went out alone this turn)
        self._outbox: dict[str, list[bytes]] = {}
        # the platform's loop, once started (each asyncio.get_running_loop is a getpid
        # system call in Python 3.11, and every first message of a turn needs the loop)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._outbox_bytes: dict[str, int] = {}
        # the platforms the last turn that sent to them sent two messages or more: a burst,
        # whose next turn (however late) batches its first message too (one envelope a turn)
        self._bursting: set[str] = set()
        # the platforms a message asking an answer went to alone, opening no batch, since
        # the last envelope opened from them or their last batch: the next one opens it
        self._lone: set[str] = set()
        # each peer's ACL key (``host.key("acl", peer)``), made once: one per trusted peer
        self._acl_keys: dict[str, str] = {}
        self.batches_lost = 0  # batched messages a failed flush did not send
        # per peer, the missing count last warned of and when (`_report_missing`)
        self._missing_warned: dict[str, tuple[int, float]] = {}
        self.missing_warn_interval = 60.0
        self.revoked = 0  # platforms removed from the trust store while running, since start
        self.unsent_revoked = 0  # messages for a platform revoked then, not sent, since start
        self._revoked: set[str] = set()  # revoked while running: what is for them is dropped
        self._unhook_trust: Callable[[], None] | None = None
        self.lane = lane
        self._lane_on = False  # the inbox is opened on the transport's thread (`_lane_take`)
        self._lane_inbox: Inbox[Any] | None = None  # its queue for the loop, then
        self._lane_lock = threading.Lock()
        # per peer: its ACL envelopes queued for the event loop or being taken there, and
        # the one the lane is deciding; the lane answers only when it is the peer's only one
        # (its key exchanges, directory statements and leave come on keys of their own,
        # which zenoh orders with none of these: not counted)
        self._lane_queued: dict[str, int] = {}
        self._lane_raw = 0  # queued unopened (`_RAW`) or taken by the loop: none answered before
        # answered on the transport's thread, to be counted and audited on the loop
        # and the replies it handed to the loop to be taken into their conversations:
        # ``(peer, entry, agent)`` and ``(peer, body, message, forgotten)``, in order
        self._lane_done: deque[tuple[Any, ...]] = deque()
        # `_lane_book` is due (the audit flush woken or ticking, or posted) and has not run
        self._lane_posted = False
        # `_lane_book` is posted to the loop for a reply and has not run: a reply is never
        # left for the audit flush's tick, where the answers' bookings may wait
        self._lane_reply_posted = False
        # the session the lane took to its message budget and asked the loop to renew once
        self._lane_renewing: object = None
        self.answered_on_thread = 0  # of ``answered_at_once``, on the transport's thread
        self.lane_replies = lane_replies
        # a reply handed to the loop waits in `_lane_done`: the loop has work, so what comes
        # meanwhile goes to it unopened, as while the inbox holds anything
        self._lane_handed = False
        self.replies_on_thread = 0  # replies opened and parsed there, taken by `_lane_book`
        self.lane_failed = 0  # bookings and hand-overs `_lane_book` skipped as they raised
        self.inbox_failed = 0  # items the inbox's consumer (`_receive`) skipped as they raised

    # for the type checker, what one part calls of another: each is defined in its
    # part (or InterfaceAgent), and mypy checks that the two signatures agree
    if TYPE_CHECKING:

        async def send(self, platform: str, message: ACLMessage) -> None: ...

        def send_now(self, platform: str, message: ACLMessage) -> bool: ...

        def sends_now(self, platform: str) -> bool: ...

        def _flush(self, platform: str, again: bool = False) -> None: ...

        def renew_if_needed(self, peer: str) -> None: ...

        @property
        def _me(self) -> str: ...

        def _peer_renewing(self, peer: str) -> bool: ...

        def _require_host(self) -> AgentPlatform: ...

        async def agree(self, peer: str) -> None: ...

        async def _renew(self, peer: str, *, announce: bool = False) -> None: ...

        async def _on_key_exchange(self, key: str, payload: bytes) -> bytes | None: ...

        def _kx_priority(self) -> None: ...

        def _count_shed(self, n: int) -> None: ...

        def _report_missing(self, now: float) -> None: ...

        def _report_kx_shed(self, now: float) -> None: ...

        def rehandshake(self, peer: str) -> None: ...

        async def _receive(self, inbox: Subscription[Any]) -> None: ...

        def _forgotten_since(self, peer: str) -> AuthenticationError: ...

        def _not_opened(self, stats: Any, exc: Exception) -> None: ...

        def _take_message(
            self, host: AgentPlatform, peer: str, state: _Sender, message: ACLMessage, now: float
        ) -> bool: ...

        def _lane_release(self, peer: str) -> None: ...

        def _lane_dropped(self, item: tuple[Any, ...]) -> None: ...

        def _lane_raw_release(self) -> None: ...

        def _lane_take(self, payload: bytes) -> tuple[str | None, Any, int] | None: ...

        def _lane_book(self, current: tuple[Any, ...] | None = None) -> bool: ...

        def _lane_failed(self, what: str, peer: str, item: Any) -> None: ...

        def _admit_now(self, host: AgentPlatform, peer: str, message: ACLMessage) -> bool: ...

        async def _malformed(
            self, host: AgentPlatform, peer: str, raw: Any, exc: MessageError
        ) -> None: ...

        def _sender(self, host: AgentPlatform, peer: str) -> _Sender: ...

        async def _limited(
            self,
            host: AgentPlatform,
            peer: str,
            sender: _Sender,
            raw: Any,
            message: ACLMessage | None,
            now: float,
        ) -> None: ...

        def _report_limited(self, peer: str, sender: _Sender, now: float) -> None: ...

        def _drop_unauthenticated(
            self, claimed: str | None, reason: str, *, stage: str | None = None
        ) -> None: ...

        def _report_unauthenticated(self, now: float) -> None: ...

        async def _admit(self, host: AgentPlatform, peer: str, message: ACLMessage) -> None: ...

        async def _watch(self, presence: Subscription[Presence]) -> None: ...

        def _report_presence_ignored(self, now: float) -> None: ...

        def _wake_flush(self) -> None: ...

        async def _flushing(self) -> None: ...

        async def _publish_audit(self, host: AgentPlatform, data: bytes) -> None: ...

        def _admit_watch(self, payload: bytes) -> bool: ...

        async def _on_watch(self, key: str, payload: bytes) -> bytes | None: ...
