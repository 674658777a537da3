"""The Interface Agent's receiving: the inbox's consumer, envelopes taken to the agents."""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING, Any

import orjson

from ._acl import (
    _SHALLOW_JSON_BYTES,
    _TRUSTED_NESTING,
    ACLMessage,
    Performative,
    _all_scalars,
    _constructed,
    _nests_less,
    _new_message,
    _quick_fields,
    _set_dict,
    _set_extra,
    _set_fields_set,
    _set_private,
    nesting_bound,
)
from ._agent import _RUNNING, LATER, Agent
from ._audit import _NAMES
from ._exceptions import AuthenticationError, MessageError, UnknownSession
from ._interface_common import (
    _ABSENT,
    _RAW,
    INITIATING,
    MAX_BATCH,
    _failure,
    _loads,
    _Sender,
    _shape,
    _written,
    log,
)
from ._interface_state import _InterfaceState
from ._security import _untrusted
from .transports import Subscription

if TYPE_CHECKING:
    from ._platform import AgentPlatform


class _Receiving(_InterfaceState):
    """What comes from other platforms: the inbox consumed, envelopes opened and taken."""

    # -- receiving ----------------------------------------------------------------------------

    async def _receive(self, inbox: Subscription[Any]) -> None:
        """The inbox's consumer: each ACL envelope opened (unless the lane did), taken.

        An item whose taking raises costs only itself: logged with what failed, counted in
        ``inbox_failed``, the lane's count it held released; the consumer goes on (else
        nothing of any peer would be taken any more)."""
        host = self._require_host()
        open_envelope = self.sessions.open
        stats = host.stats
        lane = self._lane_on
        lone = self._lone
        n = 0
        async for item in inbox:
            n += 1
            if not n & 63:
                # Getting a queued item never suspends, and dropping one is cheap: without
                # this a flood would hold the loop, and no agent would run to answer others.
                await asyncio.sleep(0)
            peer = None
            # the lane's count the item holds until it is done with: its peer's (an
            # envelope the lane opened) or one of those left unopened (`_RAW`)
            held: Any = None
            what = "opening the envelope"
            try:
                if lane:  # opened on the transport's thread (`_lane_take`)
                    if self._lane_done and self._lane_book_before(item):
                        # what the lane answered or handed over before this came is booked
                        # (and the replies taken) before it is taken: its posted booking
                        # waits behind this turn when the inbox was being drained (no
                        # wake-up of its own put it in the queue). True: a reply went back
                        # to the inbox, and this item behind it
                        continue
                    peer, body = item[0], item[1]  # (None, error): it did not open
                    if peer is _RAW:  # several lanes in this process: opened here (`_Lanes`)
                        held, peer = _RAW, None
                        try:
                            peer, body = open_envelope(body)
                        except Exception as exc:
                            held = None
                            self._lane_raw_release()
                            what = "refusing the envelope"
                            self._not_opened(stats, exc)
                            continue
                    elif peer is None:
                        what = "refusing the envelope"
                        self._not_opened(stats, body)
                        continue
                    else:
                        held = peer
                        if item[2] != self.sessions.forgotten(peer):
                            # its sessions were forgotten since it opened (revoked): refused
                            # as the loop's own open of it now would refuse it
                            held = None
                            self._lane_release(peer)
                            what = "refusing the envelope"
                            self._not_opened(stats, self._forgotten_since(peer))
                            continue
                else:
                    try:
                        peer, body = open_envelope(item.payload)
                    except Exception as exc:
                        what = "refusing the envelope"
                        self._not_opened(stats, exc)
                        continue
                what = "taking the message"
                lone.discard(peer)  # a turn of the loop after what went to it (`_sent`)
                state = self._senders.get(peer)
                if state is None:
                    state = self._sender(host, peer)
                if body[:1] != b"[":
                    with state.lock:
                        taken = self._take_now(host, peer, state, body)
                    if not taken:
                        await self._take(host, peer, state, body)
                    continue
                what = "taking the batch"
                items = await self._batch_items(host, peer, body)
                now = self._monotonic()  # one reading: the batch arrived at once
                i, end = 0, len(items)
                while i < end:
                    with state.lock:
                        done = self._take_batch(host, peer, state, items, i, now)
                    n += done - i
                    i = done
                    if i < end:  # one the quick path leaves (a limit, a refusal …): in full
                        await self._take(host, peer, state, items[i], now)
                        i += 1
                        n += 1
                    if n >= 64:
                        n = 0
                        await asyncio.sleep(0)
            except Exception:
                self._inbox_failed(what, peer, item)
            finally:
                if held is not None:
                    self._release_held(held, item)
        host._inbox_ended(inbox)

    def _release_held(self, held: Any, item: Any) -> None:
        """The lane's count ``item`` held, released; a release that raises (a fault of the
        code: the count out of step) costs only itself, else it would end the inbox's
        consumer and nothing of any peer would be taken any more."""
        try:
            if held is _RAW:
                self._lane_raw_release()
            else:
                self._lane_release(held)
        except Exception:
            self._lane_failed(
                "releasing the lane's count of a message", "?" if held is _RAW else held, item
            )

    def _lane_book_before(self, item: tuple[Any, ...]) -> bool:
        """`_lane_book` before the inbox's consumer takes ``item``; one that raises (beyond
        what it contains itself) costs only itself, and ``item`` is taken as usual."""
        try:
            return self._lane_book(item)
        except Exception:
            self._lane_failed("booking what the lane took before an envelope", "?", item)
            return False

    def _inbox_failed(self, what: str, peer: str | None, item: Any) -> None:
        """Taking one item of the inbox raised: logged once (never what it holds), counted,
        skipped."""
        self.inbox_failed += 1
        log.error(
            "interface[%s]: %s from %s failed (%s): %s",
            self._me,
            what,
            peer or "?",
            _shape(item),
            _failure(),
        )

    def _forgotten_since(self, peer: str) -> AuthenticationError:
        """What opening an envelope of ``peer`` says now that its sessions are forgotten."""
        if peer not in self.trust:
            return _untrusted(peer)
        return UnknownSession(f"the session with {peer!r} was forgotten since it opened", peer)

    def _not_opened(self, stats: Any, exc: Exception) -> None:
        """An ACL envelope that did not open: counted, audited (within budget), dropped."""
        stats.unauthenticated += 1
        if isinstance(exc, AuthenticationError):
            self._drop_unauthenticated(exc.platform, f"{exc.code}: {exc.reason}")
            if isinstance(exc, UnknownSession) and exc.platform is not None:
                self.rehandshake(exc.platform)
        else:
            self._drop_unauthenticated(None, f"malformed: {exc}")

    # -- taking: envelopes opened, parsed and handed to the agents -------------------------

    async def _batch_items(self, host: AgentPlatform, peer: str, body: bytes) -> list[Any]:
        """The messages (decoded, not yet checked) of a batch; none when it is malformed."""
        reason = None
        if len(body) > self.max_bytes:
            reason = f"batch of {len(body)} bytes exceeds the limit of {self.max_bytes}"
        else:
            try:
                items = orjson.loads(body)
            except orjson.JSONDecodeError as exc:
                reason = f"not JSON: {exc}"
            else:
                if type(items) is list and 1 <= len(items) <= MAX_BATCH:
                    return items
                reason = f"a batch is a JSON array of 1 to {MAX_BATCH} messages"
        await host.reject(body, reason)  # counted and logged; nobody to answer
        self.audit.record(verdict="dropped", **{"from": peer}, reason=reason)
        return []

    async def _take(
        self,
        host: AgentPlatform,
        peer: str,
        state: _Sender,
        raw: Any,
        now: float = 0.0,
    ) -> None:
        """One message from ``peer`` (JSON bytes, or decoded in a batch): limit, parse, admit."""
        if self.mirroring:
            body = raw if type(raw) is bytes else _written(raw)
            self._mirror.append(("acl", peer, time.time(), body))
        if state.total is not None:
            now = now or self._monotonic()
            with state.lock:
                taken = state.total.take(now)
            if not taken:
                await self._limited(host, peer, state, raw, None, now)
                return
        try:
            if type(raw) is bytes:
                message = ACLMessage.from_json(raw, max_bytes=self.max_bytes)
            else:
                message = ACLMessage.from_parsed(raw)
        except MessageError as exc:
            await self._malformed(host, peer, raw, exc)
            return
        requests = state.requests
        if requests is not None and message.performative in INITIATING:
            with state.lock:
                taken = requests.take(now)
            if not taken:
                await self._limited(host, peer, state, raw, message, now)
                return
        state.stats.accepted += 1
        try:
            if not self._admit_now(host, peer, message):
                await self._admit(host, peer, message)
        except Exception:
            # never the error's text: it may quote the message, decrypted
            log.error("interface[%s]: delivering from %s failed: %s", self._me, peer, _failure())

    def _take_now(self, host: AgentPlatform, peer: str, state: _Sender, body: bytes) -> bool:
        """`_take` of one message (JSON bytes) in the common case, at once; else False.

        The common case is `_admit_now`'s, within ``peer``'s limits: the message valid,
        one receiver here, running with room in its mailbox; no reply_to; the sender an
        agent of ``peer``; a request only to a service ``peer`` may use. Every check is
        made before anything is taken or counted, so False leaves everything as it was,
        for `_take` to decide the message in full. Taken, the message is limited,
        counted, audited and delivered as `_take` does, without its calls per step (the
        path of every request and reply that comes alone).
        """
        if self.mirroring or len(body) > self.max_bytes:
            return False
        total = state.total
        now = 0.0
        if total is not None:
            now = self._monotonic()
            if not total.ready(now):
                return False
        # `ACLMessage.from_json`, inline (its size check is made above): the quick parse
        try:
            obj = _loads(body)
        except orjson.JSONDecodeError:
            return False
        if (
            type(obj) is dict
            and (fields := _quick_fields(obj)) is not None
            and (len(body) < _SHALLOW_JSON_BYTES or nesting_bound(body) < _TRUSTED_NESTING)
        ):
            message = _constructed(ACLMessage, fields, set(obj))
        else:
            try:
                message = ACLMessage.from_parsed(obj, nesting=nesting_bound(body))
            except MessageError:
                return False
        return self._take_message(host, peer, state, message, now)

    def _take_message(
        self, host: AgentPlatform, peer: str, state: _Sender, message: ACLMessage, now: float
    ) -> bool:
        """`_take_now` of a message parsed already, its total limit found ready at ``now``."""
        total, requests = state.total, state.requests
        # a parsed message holds every field in its __dict__: read there, each read is a
        # dict lookup rather than a pass through pydantic's attribute hook
        fields = message.__dict__
        receivers = fields["receivers"]
        if len(receivers) != 1 or fields["reply_to"]:
            return False
        receiver = receivers[0]
        sender = fields["sender"]
        here = host.name
        at = receiver.rpartition("@")
        if at[2] != here or sender.rpartition("@")[2] != peer or peer == here:
            return False
        agent = host._agents.get(at[0])
        if agent is None or agent._state != _RUNNING:  # `agent.running`, inline
            return False
        mailbox = agent._mailbox
        if len(mailbox._items) >= mailbox.maxlen >> 1:
            return False
        performative = fields["performative"]
        initiating = performative in INITIATING
        if initiating:
            if requests is not None and not requests.ready(now):
                return False
            df = host.df
            if df is None or not df.reachable(receiver, peer):
                return False
            if requests is not None:
                requests.tokens -= 1.0
        if total is not None:
            total.tokens -= 1.0
        state.stats.accepted += 1
        audit = self.audit
        # accepted_entry, inline (one receiver, this sender)
        conversation_id = fields["conversation_id"]
        entry = (time.time(), peer, sender, receiver, _NAMES[performative], conversation_id)
        audit.add_accepted((entry,))
        stats = host.stats
        stats.received_remote += 1
        if (
            agent.answer_at_once is not None
            and initiating  # admitted by the directory's access check, as no answer is
            and not mailbox._items
            and mailbox._waiter is not None  # its receive loop is in no handler
            and not agent._handlers_starting  # nor will a concurrent handler's task
            and self.sends_now(peer)  # else the read would be made twice
            and fields["in_reply_to"] is None
            and conversation_id not in agent._by_conv
            and self._answer_at_once(host, peer, agent, message)
        ):
            stats.local += 1
            return True
        try:
            agent._deliver(message)  # running, room in its mailbox: taken
        except Exception:
            log.error("interface[%s]: delivering from %s failed: %s", self._me, peer, _failure())
        else:
            stats.local += 1
        return True

    def _answer_at_once(
        self, host: AgentPlatform, peer: str, agent: Agent, message: ACLMessage
    ) -> bool:
        """Answer ``message`` by ``agent.answer_at_once`` and send it now; False: not so.

        Called for an admitted message only when the mailbox route would queue it (not a
        reply to one of the agent's conversations) and nothing waits before it: False
        leaves it to the mailbox, which then decides it as if this was never asked.
        """
        try:
            content = agent.answer_at_once(message)  # type: ignore[misc]
        except Exception:  # the handler meets it again and answers for it
            return False
        if content is LATER:
            return False
        try:
            reply = message.reply(Performative.INFORM, content, sender=agent.aid)
            if not self.send_now(peer, reply):
                return False
        except Exception:  # content an inform cannot carry: the handler's path says why
            return False
        agent_stats = agent.stats
        agent_stats.received += 1
        agent_stats.handled += 1
        agent_stats.answered_at_once += 1
        host.stats.sent_remote += 1
        return True

    def _take_batch(
        self,
        host: AgentPlatform,
        peer: str,
        state: _Sender,
        items: list[Any],
        i: int,
        now: float,
    ) -> int:
        """`_take` of a batch's decoded messages from ``items[i]`` on, while none needs a wait.

        Returns the index of the first message it left (``len(items)``: none), untouched,
        for `_take`: a bad message, a limit reached, a receiver that is not ready, anything
        but the common case of `_admit`. Each message taken is checked, counted against
        the limits, audited and delivered as `_take` would, in one loop without a call per
        step (this is the path a flood takes, message after message); the messages for
        one agent are handed over together (`Agent._deliver_batch`), once decided.
        """
        end = len(items)
        if self.mirroring:
            return i
        total, requests = state.total, state.requests
        if total is not None:
            total.ready(now)  # refilled once: ``now`` stays the same for the batch
        from_parsed = ACLMessage.from_parsed
        agents = host._agents
        here = host.name
        if peer == here:  # a message claiming this platform's sender: `_take` drops it
            return i
        df = host.df
        audit = self.audit
        entries: list[tuple[Any, ...]] = []  # logged together, at the end
        add_entry = entries.append
        ts = time.time()  # one decision time for the batch, as one arrival time
        start = i
        # The messages taken for one agent, handed over together when the next is for
        # another one, or at the end (nothing runs in between: the same as one by one).
        run: list[ACLMessage] = []
        run_agent: Agent | None = None
        # what was found of the last receiver and sender, unchanged within the batch (an
        # agent neither starts nor stops meanwhile): a batch is mostly one conversation
        last_receiver: str | None = None
        last_sender: str | None = None
        room = 0  # how many more the receiver's mailbox takes before it is half full
        # A batch is mostly one header (all but the content) again and again: a message
        # whose header equals that of the last one taken (the first of a run) is valid
        # and admitted as that one was, its fields a copy of that one's: only what is
        # its own is checked (content's depth, the limits' tokens, room in the mailbox).
        # The first header that differs ends this for the batch (requests, replies vary).
        head: dict[str, Any] | None = None  # the header of the message taken last
        head_fields: dict[str, Any] = {}  # its fields
        head_entry: tuple[Any, ...] = ()  # its audit entry
        head_names: set[str] = set()  # its keys (`__pydantic_fields_set__`)
        head_bare = False  # whether it has no content
        head_initiating = False
        reuse = True
        try:
            while i < end:
                if total is not None and total.tokens < 1.0:
                    break
                obj = items[i]
                if head is not None and type(obj) is dict:
                    rest = obj.copy()
                    content = rest.pop("content", _ABSENT)
                    bare = content is _ABSENT  # no content (None, as the model's default)
                    if bare:
                        content = None
                    # equal to a header taken: valid, but for a number equal to its ``v``
                    # that is no int (1.0, true); `_nests_less`'s common case (a dict of
                    # scalars) told here, without its call
                    if (
                        rest == head
                        and type(rest["v"]) is int
                        and (
                            (type(content) is dict and _all_scalars(map(type, content.values())))
                            or _nests_less(content)
                        )
                    ):
                        if room <= 0:
                            break
                        if head_initiating and requests is not None:
                            if not requests.ready(now):
                                break
                            requests.tokens -= 1.0
                        if total is not None:
                            total.tokens -= 1.0
                        copied = head_fields.copy()
                        # its own list, the decoded batch's, not copied: nothing else
                        # keeps the batch's items once they are taken
                        copied["receivers"] = rest["receivers"]
                        copied["content"] = content
                        add_entry(head_entry)
                        # `_constructed`, inline; its keys those of the header's message
                        # when both have a content or neither has: a copy of that one's set
                        message = _new_message(ACLMessage)
                        _set_dict(message, copied)
                        _set_fields_set(
                            message, head_names.copy() if bare is head_bare else set(obj)
                        )
                        _set_extra(message, None)
                        _set_private(message, None)
                        run.append(message)
                        room -= 1
                        i += 1
                        continue
                    head = None
                    reuse = False
                # `from_parsed`'s quick path, inline
                quick = False
                if (
                    type(obj) is dict
                    and (fields := _quick_fields(obj)) is not None
                    and _nests_less(fields["content"])  # each message's depth, not the batch's
                ):
                    message = _constructed(ACLMessage, fields, set(obj))
                    quick = True
                else:
                    try:
                        message = from_parsed(obj)
                    except MessageError:
                        break
                    fields = message.__dict__
                # the message's fields read from its dict: cheaper than its attributes
                receivers = fields["receivers"]
                if len(receivers) != 1 or fields["reply_to"]:
                    break
                receiver = receivers[0]
                if receiver != last_receiver:
                    at = receiver.rpartition("@")
                    if at[2] != here:
                        break
                    agent = agents.get(at[0])
                    if agent is None or not agent.running:
                        break
                    if agent is not run_agent:
                        if run_agent is not None and run:
                            run_agent._deliver_batch(run)
                            run = []
                        run_agent = agent
                    mailbox = agent._mailbox
                    room = (mailbox.maxlen >> 1) - len(mailbox._items) - len(run)
                    last_receiver = receiver
                sender = fields["sender"]
                if sender != last_sender:
                    if sender.rpartition("@")[2] != peer:
                        break
                    last_sender = sender
                if room <= 0:  # counting those not yet handed over
                    break
                performative = fields["performative"]
                initiating = performative in INITIATING
                if initiating:
                    if requests is not None and not requests.ready(now):
                        break
                    if df is None or not df.reachable(receiver, peer):
                        break
                    if requests is not None:
                        requests.tokens -= 1.0
                if total is not None:
                    total.tokens -= 1.0
                # accepted_entry, inline (one receiver, this sender)
                entry = (
                    ts,
                    peer,
                    sender,
                    receiver,
                    _NAMES[performative],
                    fields["conversation_id"],
                )
                add_entry(entry)
                run.append(message)  # running, room in its mailbox: taken
                room -= 1
                i += 1
                if reuse and quick:
                    if "v" in obj and "reply_to" not in obj and "reply_by" not in obj:
                        head = obj.copy()
                        head.pop("content", None)
                        head_fields, head_entry, head_initiating = fields, entry, initiating
                        head_names = set(obj)  # its own: the message's is the message's
                        head_bare = "content" not in obj
                    else:
                        reuse = False
        finally:
            taken = i - start
            if taken:
                audit.add_accepted(entries)  # one per message taken
                state.stats.accepted += taken
                stats = host.stats
                stats.received_remote += taken
                stats.local += taken
            if run_agent is not None and run:
                run_agent._deliver_batch(run)  # audited first, as `_admit_now` does
        return i
