"""The Interface Agent's lane: plain reads answered on the transport's thread."""

from __future__ import annotations

import contextlib
import time
from collections import deque
from typing import TYPE_CHECKING, Any, cast

import orjson

from ._acl import (
    _SHALLOW_JSON_BYTES,
    _TRUSTED_NESTING,
    ACLMessage,
    _constructed,
    _quick_fields,
    nesting_bound,
    reply_json,
)
from ._agent import _RUNNING, LATER
from ._audit import _NAMES
from ._exceptions import AgentError
from ._interface_common import (
    _ANSWERED,
    _HANDED,
    _INFORM,
    _LANES,
    _LEFT,
    _RAW,
    INITIATING,
    _failure,
    _loads,
    _Sender,
    _shape,
    _Written,
    log,
)
from ._interface_state import _InterfaceState

if TYPE_CHECKING:
    from ._platform import AgentPlatform


class _Lane(_InterfaceState):
    """The lane: envelopes opened, and plain reads answered, on the transport's thread."""

    # -- the lane: plain reads answered on the transport's thread ---------------------

    def _lane_release(self, peer: str) -> None:
        """One message of ``peer`` the loop or the lane took is done with."""
        with self._lane_lock:
            left = self._lane_queued[peer] - 1
            if left:
                self._lane_queued[peer] = left
            else:
                del self._lane_queued[peer]

    def _lane_dropped(self, item: tuple[Any, ...]) -> None:
        """The inbox was full and dropped ``item`` (oldest first): the loop never takes it."""
        if item[0] is _RAW:
            self._lane_raw_release()
        elif item[0] is not None:
            self._lane_release(item[0])

    def _lane_raw_release(self) -> None:
        """An unopened item (`_RAW`) the loop took is done with (or was dropped)."""
        with self._lane_lock:
            self._lane_raw -= 1

    def _lane_take(self, payload: bytes) -> tuple[str | None, Any, int] | None:
        """On zenoh's thread: open ``payload``; a plain read answered here (None), else
        ``(peer, body, forgotten)`` (``(None, error, 0)``: it did not open) for the event
        loop, in order (`SessionTable.open_noting`: the loop refuses it if the peer's
        sessions were forgotten since).

        An envelope opens here while nothing waits for the loop; else (or with several lanes
        in this process, `_Lanes`) it goes unopened (`_RAW`), in order, and the loop opens
        it under the same table lock. A read is answered here only while nothing of its peer
        is queued for the loop or taken there (it overtakes nothing), by `_lane_answer`.
        """
        inbox = self._lane_inbox
        if (
            _LANES.open > 1
            or self._lane_raw
            or self._lane_handed
            or (inbox is not None and inbox._items)
        ):
            # The loop is draining (or several lanes share this process): it opens this
            # one too. Opening it here would only hand the GIL to and fro (a burst of
            # replies at an asker, a flood) where the lane gains nothing: no answer here
            # can go before what waits for the loop.
            with self._lane_lock:
                self._lane_raw += 1
            return _RAW, payload, 0
        try:
            peer, body, forgets = self.sessions.open_noting(payload)
        except Exception as exc:  # the loop counts and audits it
            return None, exc, 0
        # the lock taken and released by its methods, not by `with`: ~0.8 k instructions
        # less a section on the path of every envelope the lane opens (and of what it
        # answers, `_lane_answer`, or hands over to the loop, `_lane_reply`). On zenoh's
        # thread only: on the loop's (the main thread) a signal's handler runs right after
        # a call returns, and an interrupt raised between `acquire()` and `try` would leave
        # the lock held for ever; `with` leaves no such gap (`_lane_book`, `_lane_take_reply`)
        lock = self._lane_lock
        lock.acquire()
        try:
            queued = self._lane_queued.get(peer, 0)
            self._lane_queued[peer] = queued + 1
            raw = self._lane_raw
        finally:
            lock.release()
        if queued == 0 and not raw:
            try:
                answered = self._lane_answer(peer, body, forgets)
            except Exception:  # never into zenoh's thread: the loop decides it
                # never the error's text: it may quote the body, decrypted
                log.error(
                    "interface[%s]: answering %s on the receiving thread: %s",
                    self._me,
                    peer,
                    _failure(),
                )
                answered = _LEFT
            if answered is _ANSWERED:
                lock.acquire()  # `_lane_release`, inline: every answer the lane puts
                try:
                    left = self._lane_queued[peer] - 1
                    if left:
                        self._lane_queued[peer] = left
                    else:
                        del self._lane_queued[peer]
                finally:
                    lock.release()
                return None
            if answered is _HANDED:  # a reply: its count stands until `_lane_book` takes it
                return None
        return peer, body, forgets  # its count stands until the loop has taken it

    def _lane_answer(self, peer: str, body: bytes, forgets: int) -> object:
        """`_take_now` and `_answer_at_once` of a plain read, on zenoh's thread: `_ANSWERED`;
        a reply an open conversation waits for handed to the loop (`_lane_reply`):
        `_HANDED`; else `_LEFT`, nothing taken (the loop then decides it as always).

        The same checks, limits and answer, reading only what is safe beside the loop:
        its dicts and sets by one lookup each, the sender's buckets under their lock, the
        sessions under the table's, the directory's decisions made before
        (`DirectoryFacilitator.reachable_now`), the agent's `Agent.answer_on_thread`, and
        a publisher the loop declared. What the loop alone changes (the counts, the audit
        log, a session's renewal) it does in `_lane_book`, booked before the answer is put
        and run at the audit flush's next tick (or before the loop's next take).
        """
        host = self._host
        if host is None or self.mirroring or len(body) > self.max_bytes or body[:1] == b"[":
            return _LEFT
        state = self._senders.get(peer)
        if state is None:
            return _LEFT
        try:
            obj = _loads(body)
        except orjson.JSONDecodeError:
            return _LEFT
        if (
            type(obj) is not dict
            or (fields := _quick_fields(obj)) is None
            or (len(body) >= _SHALLOW_JSON_BYTES and nesting_bound(body) >= _TRUSTED_NESTING)
        ):
            return _LEFT  # the full model's parse, on the loop
        message = _constructed(ACLMessage, fields, set(obj))
        # ``fields`` is the message's __dict__: each read a dict lookup, not a pass through
        # pydantic's attribute hook
        performative = fields["performative"]
        if performative not in INITIATING:
            return _HANDED if self._lane_reply(peer, body, message, fields, forgets) else _LEFT
        receivers = fields["receivers"]
        if len(receivers) != 1 or fields["reply_to"] or fields["in_reply_to"] is not None:
            return _LEFT
        receiver = receivers[0]
        sender = fields["sender"]
        here = host.name
        at = receiver.rpartition("@")
        if at[2] != here or sender.rpartition("@")[2] != peer or peer == here:
            return _LEFT
        agent = host._agents.get(at[0])
        if agent is None or agent._state != _RUNNING:
            return _LEFT
        answer = agent.answer_on_thread
        mailbox = agent._mailbox
        if (
            answer is None
            or agent.answer_at_once is None
            or mailbox._items
            or mailbox._waiter is None  # its receive loop is in a handler
            or agent._handlers_starting
            or fields["conversation_id"] in agent._by_conv
        ):
            return _LEFT
        df = host.df
        if df is None or not df.reachable_now(receiver, peer):
            return _LEFT
        transport = host.transport
        key = self._acl_keys.get(peer)  # made by the loop's first send to it
        if key is None or peer in self._outbox:
            # a batch of the loop's for it this turn: the answer would join it there (a
            # burst of the loop's sends is no reason: the lane's answer is in no turn)
            return _LEFT
        put = transport.declared_publisher(key)
        if put is None:
            return _LEFT
        try:
            content = answer(message)
            if content is LATER:
                return _LEFT
            # the reply's bytes alone: the message is made only if the put fails (resent)
            reply = reply_json(message, _INFORM, content, agent.aid)
            if reply is None:
                reply = message.reply(_INFORM, content, sender=agent.aid).to_json()
        except Exception:  # the loop's `answer_at_once` and handler meet it again
            return _LEFT
        total, requests = state.total, state.requests
        now = 0.0 if total is None else self._monotonic()
        lock = state.lock
        if not lock.acquire(False):
            return _LEFT  # the loop is taking from these buckets: it decides this one too
        try:
            if (total is not None and not total.ready(now)) or (
                requests is not None and not requests.ready(now)
            ):
                return _LEFT  # limited: refused, counted and audited on the loop
            if requests is not None:
                requests.tokens -= 1.0
            if total is not None:
                total.tokens -= 1.0
        finally:
            lock.release()
        entry = (
            time.time(),
            peer,
            sender,
            receiver,
            _NAMES[performative],
            fields["conversation_id"],
        )
        try:
            sealed = self._seal(peer, reply)
        except Exception:  # no session, or one past its lifetime: the loop decides it
            self._lane_give_back(state)
            return _LEFT
        # Booked before the answer leaves: whatever the peer sends once it has the answer
        # reaches the loop behind this booking (`_receive`'s check, or the posted booking's
        # FIFO place when no audit flush runs).
        done = (peer, entry, agent)
        lane_lock = self._lane_lock  # not `with`: see `_lane_take`
        lane_lock.acquire()
        try:
            self._lane_done.append(done)
            posted, self._lane_posted = self._lane_posted, True
        finally:
            lane_lock.release()
        if not posted:
            if self._flush_loop is not None:
                # booked at the audit flush's next tick (it writes the record then anyway),
                # or before the loop takes the peer's next message (`_receive`): a wake-up
                # of the loop per answer cost it more than the answer (bench scale)
                self._wake_flush()
            else:
                loop = self._loop
                try:
                    if loop is not None:
                        loop.call_soon_threadsafe(self._lane_book)
                except RuntimeError:  # the loop is closed: nobody reads the counts any more
                    pass
        session = self.sessions._tx.get(peer)  # the one just sealed on (one lookup, no lock)
        if (
            session is not None
            and session._n + session._bn >= self.policy.renew_after_messages
            and self._lane_renewing is not session
        ):
            # past its message budget: booked (and so renewed) now, once a session, not at
            # the flush's tick, which may come many answers on that session later
            self._lane_renewing = session
            with contextlib.suppress(RuntimeError):  # the loop is closed: nothing renews
                if (loop := self._loop) is not None:
                    loop.call_soon_threadsafe(self._lane_book)
        try:
            put(sealed)
        except Exception as exc:  # a transport closing
            booked = True
            with self._lane_lock:
                pending = self._lane_done
                for i, item in enumerate(pending):
                    if item is done:  # not booked yet: taken back, the loop decides it
                        del pending[i]
                        booked = False
                        if not pending:
                            # nothing left to book: the next answer wakes a booking again
                            # (a flush woken for this one finds none and does not clear it)
                            self._lane_posted = False
                        break
            if booked:
                # booked already (the loop ran between): counted once, as answered; the
                # loop sends the answer its own way (a publisher evicted meanwhile is
                # declared again there)
                log.info("interface[%s]: the lane's put to %s failed: %s", self._me, peer, exc)
                try:
                    loop = self._loop
                    if loop is not None:
                        # the very bytes counted and audited: ``content`` may have changed
                        # since they were written (an agent's shared answer), a copy or a
                        # message made of it now would send what was not counted
                        answered = cast(ACLMessage, _Written(reply))
                        loop.call_soon_threadsafe(self._lane_resend, peer, answered)
                except RuntimeError:  # the loop is closed: nobody waits for the answer
                    pass
                return _ANSWERED
            self._lane_give_back(state)
            return _LEFT
        return _ANSWERED

    def _lane_resend(self, peer: str, answer: ACLMessage) -> None:
        """On the loop: send an answer the lane booked but could not put (`send`; its bytes
        as the lane wrote them, `_Written`)."""
        host = self._host
        if host is None or self.send_now(peer, answer):
            return
        try:
            host.spawn(self._lane_send(peer, answer), "interface.lane-resend")
        except AgentError:  # the platform is closing: nobody waits for the answer
            pass

    async def _lane_send(self, peer: str, answer: ACLMessage) -> None:
        try:
            await self.send(peer, answer)
        except Exception as exc:  # as a handler's answer that could not be sent
            log.warning("interface[%s]: could not send an answer to %s: %s", self._me, peer, exc)

    @staticmethod
    def _lane_give_back(state: _Sender) -> None:
        """The tokens the lane took for a message it leaves to the loop after all."""
        total, requests = state.total, state.requests
        with state.lock:
            if requests is not None:
                requests.tokens = min(requests.burst, requests.tokens + 1.0)
            if total is not None:
                total.tokens = min(total.burst, total.tokens + 1.0)

    def _lane_reply(
        self, peer: str, body: bytes, message: ACLMessage, fields: dict[str, Any], forgets: int
    ) -> bool:
        """On zenoh's thread: hand ``message``, a reply an open conversation waits for, to
        the loop's `_lane_book`, which takes it (`_lane_take_reply`); False: not such a one.

        Only read here (one dict lookup each); the loop decides everything again.
        ``fields`` is the message's __dict__: each read a dict lookup, not a pass through
        pydantic's attribute hook.
        """
        if not self.lane_replies or fields["reply_to"]:
            return False
        host = self._host
        receivers = fields["receivers"]
        if host is None or len(receivers) != 1:
            return False
        here = host.name
        at = receivers[0].rpartition("@")
        sender = fields["sender"]
        if at[2] != here or sender.rpartition("@")[2] != peer or peer == here:
            return False
        agent = host._agents.get(at[0])
        if agent is None or agent._state != _RUNNING:
            return False
        conv = None
        if (key := fields["in_reply_to"]) is not None:
            conv = agent._by_reply.get(key)
        if conv is None and (key := fields["conversation_id"]) is not None:
            conv = agent._by_conv.get(key)
        # `conv.accepts(message)`, inline, as `Agent._deliver` has it
        if (
            conv is None
            or conv.closed
            or ((peers := conv.peers) is not None and sender not in peers)
            or ((rw := fields["reply_with"]) is not None and rw in conv._keys)
        ):
            # a reply nobody waits for, or one its conversation refuses (not from one of
            # its peers): the loop's way, as any other message
            return False
        loop = self._loop
        if loop is None:
            return False
        lock = self._lane_lock  # not `with`: see `_lane_take`
        lock.acquire()
        try:
            self._lane_done.append((peer, body, message, forgets))
            self._lane_handed = True
            posted, self._lane_reply_posted = self._lane_reply_posted, True
        finally:
            lock.release()
        if not posted:
            try:
                loop.call_soon_threadsafe(self._lane_book)
            except RuntimeError:  # the loop is closed: nobody waits for the reply
                pass
        return True

    def _lane_take_reply(
        self, host: AgentPlatform, peer: str, body: bytes, message: ACLMessage, forgets: int
    ) -> bool:
        """On the loop: what `_receive` does with a reply the lane opened and parsed; False:
        nothing taken, `_receive` must take it in full (`_lane_book` queues it back)."""
        if forgets != self.sessions.forgotten(peer):
            # revoked since it opened: refused as `_receive` refuses it (released last: one
            # that raises is released by `_lane_book`, once)
            self._not_opened(host.stats, self._forgotten_since(peer))
            self._lane_release(peer)
            return True
        if self.mirroring or len(body) > self.max_bytes:
            return False
        state = self._senders.get(peer)
        if state is None:
            return False
        total = state.total
        with state.lock:  # `with` on the loop's thread: see `_lane_take`
            now = 0.0
            if total is not None:
                now = self._monotonic()
                if not total.ready(now):
                    return False
            taken = self._take_message(host, peer, state, message, now)
        if taken:
            with self._lane_lock:  # `_lane_release`, inline: every reply the lane hands over
                left = self._lane_queued[peer] - 1
                if left:
                    self._lane_queued[peer] = left
                else:
                    del self._lane_queued[peer]
            self.replies_on_thread += 1
        return taken

    def _lane_book(self, current: tuple[Any, ...] | None = None) -> bool:
        """On the loop: count, audit and renew for what the lane answered, as `_take_now` would,
        and take the replies it handed over; True: one went back to the inbox (the loop
        takes it in full), with ``current``, the item `_receive` took, behind it.

        A booking or hand-over that raises costs only itself: logged with what failed,
        counted in ``lane_failed``, its peer's count released; the others are made."""
        inbox = self._lane_inbox
        with self._lane_lock:  # `with` on the loop's thread: see `_lane_take`
            if (
                current is None
                and self._lane_handed
                and self._lane_on
                and inbox is not None
                and inbox._items
            ):
                # A reply handed over, and what came after it already queued: the inbox's
                # consumer books it before its next take, in the same turn as what follows
                # it, as it takes a reply and what follows from the inbox (a duplicate is
                # then in the conversation before its task runs, not late after it)
                return False
            self._lane_posted = self._lane_reply_posted = self._lane_handed = False
            done = self._lane_done
            lone = None
            if len(done) == 1 and len(done[0]) == 4:
                # one reply alone, nothing booked before it (an asker's round trip): taken
                # out of the queue the lane keeps, no new one made for it
                lone = done.popleft()
            else:
                self._lane_done = deque()
        host = self._host
        if host is None:
            if lone is None:  # the queue swapped out (the lane's own is not touched here)
                done.clear()
            return False
        if lone is not None:
            peer, body, message, forgets = lone
            self._lone.discard(peer)  # a turn of the loop after what went to it (`_sent`)
            try:
                if self._lane_take_reply(host, peer, body, message, forgets):
                    return False
            except Exception:
                self._lane_failed("taking the reply handed over", peer, message)
                self._lane_release(peer)
                return False
            again: list[tuple[Any, ...]] = [(peer, body, forgets)]  # taken in full, as below
            if current is not None:
                again.append(current)
            inbox = self._lane_inbox
            if inbox is not None:
                inbox.put_front(again)
            return True
        stats = host.stats
        entries: list[tuple[Any, ...]] = []
        peers = set()
        back: list[tuple[Any, ...]] = []  # replies `_receive` takes in full after all
        behind: set[str] = set()  # their peers: what follows of them goes back too
        while done:
            item = done.popleft()
            if len(item) == 4:  # a reply (`_lane_reply`)
                if entries:  # the records in arrival order
                    self._lane_records(entries)
                    entries = []
                peer, body, message, forgets = item
                self._lone.discard(peer)  # a turn of the loop after what went to it (`_sent`)
                if peer in behind:
                    back.append((peer, body, forgets))
                    continue
                try:
                    taken = self._lane_take_reply(host, peer, body, message, forgets)
                except Exception:
                    self._lane_failed("taking the reply handed over", peer, message)
                    self._lane_release(peer)
                    continue
                if not taken:
                    back.append((peer, body, forgets))
                    behind.add(peer)
                continue
            peer, entry, agent = item
            try:
                state = self._senders.get(peer)
                if state is not None:
                    state.stats.accepted += 1
                stats.received_remote += 1
                stats.local += 1
                stats.sent_remote += 1
                agent_stats = agent.stats
                agent_stats.received += 1
                agent_stats.handled += 1
                agent_stats.answered_at_once += 1
            except Exception:
                self._lane_failed("counting the answer", peer, entry)
            self.answered_on_thread += 1
            entries.append(entry)
            peers.add(peer)
        if entries:
            self._lane_records(entries)
        for peer in peers:
            self._lone.discard(peer)  # its request, answered on the lane, came after (`_sent`)
            try:
                self.renew_if_needed(peer)
            except Exception:
                self._lane_failed("renewing the session of its answers", peer, None)
        if not back:
            return False
        if current is not None:
            back.append(current)
        if inbox is not None:
            inbox.put_front(back)
        return True

    def _lane_records(self, entries: list[tuple[Any, ...]]) -> None:
        """The audit records of what the lane answered; one add that raises costs only itself
        (not made again one by one: records kept before it raised would be doubled)."""
        try:
            self.audit.add_accepted(entries)
        except Exception:
            self._lane_failed(f"recording {len(entries)} answers", entries[0][1], entries[0])

    def _lane_failed(self, what: str, peer: str, item: Any) -> None:
        """One booking or hand-over of `_lane_book` raised: logged once (never what it
        holds), counted, skipped."""
        self.lane_failed += 1
        log.error(
            "interface[%s]: %s from %s failed (%s): %s",
            self._me,
            what,
            peer,
            _shape(item),
            _failure(),
        )
