"""The two decoders under fuzz, at their real entry points, driven one input at a time.

`InterfaceTarget`: platform ``uav-b`` with its Interface Agent, on a MemoryHub; each input
is published on ``dyknow/demo/v1/acl/uav-b`` with a plain transport, so it arrives exactly
as the transport hands envelopes to the Interface Agent's receive loop.

`ImportTarget`: ``uav-b``'s import proxy with a real SessionTable; each input is
published on ``dyknow/demo/v1/stream/uav-b/<sender>/<label>`` and reaches the proxy's
receive loop (open, unpack, inject) the same way.

Both hold ``uav-a``'s real keys and a session with ``uav-b``, so an input can also be a
*correctly sealed* envelope whose inside is garbage: the fuzz then reaches the inner
decoders (the ACL message, the sample batch), not only the MAC check.

Each ``feed`` returns how the input was handled and raises `Crash` when it was not: an
exception escaped a decoder (logged as an error, or a non-authentication error from the
envelope check), the receive task died, or no decision was recorded within ``timeout``
seconds (blocked). The targets run their own event loop, so they serve hypothesis tests
and atheris harnesses alike (neither runs inside a loop).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

import orjson

from agents import AgentPlatform, ServiceDescription, on_request, wire_key
from agents._acl import MAX_MESSAGE_BYTES, ACLMessage, Performative
from agents._agent import Agent
from agents._exceptions import AuthenticationError
from agents._interface import MAX_BATCH, InterfaceAgent
from agents._security import Handshake, KeyPair, SecurityPolicy, SessionTable, TrustStore
from agents.transports import MemoryHub, MemoryTransport, Message, Subscription
from dyknow_core import DyKnowInstance
from federation import ImportProxy, TableSessions
from federation._batch import pack_batch

FED = "demo"
ME = "uav-b"
PEER = "uav-a"
SEM = "car5-state"
OTHER_SEM = "car6-state"
# uav-a's own policy lets it seal bodies beyond the receiver's limit: the "huge" inputs must
# be authentic, or the MAC check would stop them before the size check is reached
BIG_POLICY = SecurityPolicy(max_body_bytes=4 * MAX_MESSAGE_BYTES)

_KEYS: dict[str, KeyPair] = {}


def keys(name: str) -> KeyPair:
    """The key pair of ``name`` (one per process: key generation is not what is fuzzed)."""
    if name not in _KEYS:
        _KEYS[name] = KeyPair.generate(name)
    return _KEYS[name]


def trust() -> TrustStore:
    """A fresh copy of the federation's trust file: uav-a, uav-b and uav-c."""
    return TrustStore(FED, {n: keys(n).public_key for n in (PEER, ME, "uav-c")})


class Crash(AssertionError):
    """A decoder did not handle an input: it raised, killed its task or blocked."""


class _Errors(logging.Handler):
    """Keeps the error records (``log.exception``) of the modules under test."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


class _Echo(Agent):
    """Answers ``demo`` requests: the legitimate service the fuzz must not disturb."""

    @on_request("demo")
    async def _echo(self, message: ACLMessage) -> Any:
        return {"echo": message.content}


class _Target:
    """What both targets share: the loop, the error watch, the tallies."""

    loggers: tuple[str, ...] = ()

    def __init__(self, timeout: float) -> None:
        self.timeout = timeout
        self.loop = asyncio.new_event_loop()
        self.stack = contextlib.AsyncExitStack()
        self.outcomes: Counter[str] = Counter()
        self.slowest = 0.0
        self._errors = _Errors()
        self._foreign: list[BaseException] = []  # non-authentication errors from open
        for name in self.loggers:
            logging.getLogger(name).addHandler(self._errors)

    @property
    def inputs(self) -> int:
        """How many inputs were fed."""
        return sum(self.outcomes.values())

    def feed(self, payload: bytes, **where: Any) -> str:
        """Hand ``payload`` to the decoder as the transport would; how it was handled."""
        started = time.perf_counter()
        try:
            outcome = self.loop.run_until_complete(self._feed(payload, **where))
        except TimeoutError:
            raise Crash(
                f"no decision within {self.timeout} s for {payload[:80]!r}… (blocked)"
            ) from None
        self.slowest = max(self.slowest, time.perf_counter() - started)
        self._check(payload)
        self.outcomes[outcome] += 1
        return outcome

    def seal(self, body: bytes) -> bytes:
        """``body`` sealed by uav-a for uav-b (binary for the import target)."""
        raise NotImplementedError

    async def _feed(self, payload: bytes, **where: Any) -> str:
        raise NotImplementedError

    def _alive(self) -> bool:
        raise NotImplementedError

    def _check(self, payload: bytes) -> None:
        if self._errors.records:
            rec = self._errors.records[0]
            trace = logging.Formatter().formatException(rec.exc_info) if rec.exc_info else ""
            raise Crash(f"error logged for {payload[:80]!r}…: {rec.getMessage()}\n{trace}")
        if self._foreign:
            exc = self._foreign[0]
            raise Crash(f"envelope check raised {type(exc).__name__}: {exc} for {payload[:80]!r}…")
        if not self._alive():
            raise Crash(f"the receive task ended after {payload[:80]!r}…")

    def summary(self, name: str) -> str:
        """One line of figures: inputs, crashes (always 0 here), and how they were handled."""
        parts = ", ".join(f"{n} {k}" for k, n in sorted(self.outcomes.items()))
        return (
            f"fuzz {name}: {self.inputs} inputs, 0 crashes, {parts} "
            f"(slowest {self.slowest * 1000:.1f} ms)"
        )

    def close(self) -> None:
        """Close everything and the loop."""
        for name in self.loggers:
            logging.getLogger(name).removeHandler(self._errors)
        try:
            self.loop.run_until_complete(self.stack.aclose())
        finally:
            self.loop.close()

    async def _until(self, predicate: Callable[[], Any]) -> None:
        async with asyncio.timeout(self.timeout):
            # the decisions are counters in memory, with no event to await: poll them
            spins = 0
            while not predicate():
                spins += 1
                await asyncio.sleep(0 if spins < 50 else 0.001)


# --------------------------------------------------------------------------- interface


class InterfaceTarget(_Target):
    """uav-b's Interface Agent fed raw envelopes; uav-a (real keys) seals and reads replies.

    Outcomes: ``dropped+counted`` (audited or, for unauthentic garbage beyond the audit's
    budget, counted; nothing answered), ``not-understood`` (a malformed
    message from an authenticated sender: audited as refused, counted as malformed by the
    platform, answered), ``refused`` (access control answered a refuse), ``accepted``,
    ``rate-limited`` (over the sender's rate limit: counted).
    """

    # agents._agent too: an agent of uav-b crashing on what a peer sent is a crash as well
    loggers = ("agents._interface", "agents._platform", "agents._agent")

    def __init__(self, timeout: float = 5.0) -> None:
        super().__init__(timeout)
        self.answers: Counter[str] = Counter()  # performatives uav-a received from uav-b
        self.unauthentic = 0  # inputs dropped because their envelope did not open
        self._sealed: dict[bytes, bytes] = {}  # envelopes sealed here, and their bodies
        self.loop.run_until_complete(self._open())

    async def _open(self) -> None:
        hub = MemoryHub()
        t = await self.stack.enter_async_context(hub.transport())
        channel = InterfaceAgent(keys(ME), trust(), publish_audit=False)
        original_open = channel.sessions.open

        def probed_open(envelope: bytes | str) -> tuple[str, bytes]:
            # the receive loop turns any exception into a "malformed" drop: a decoder that
            # raises something else than a refusal is a bug that the loop would hide
            try:
                return original_open(envelope)
            except AuthenticationError:
                raise
            except Exception as exc:
                self._foreign.append(exc)
                raise

        channel.sessions.open = probed_open  # type: ignore[method-assign]
        self.ia = channel
        self.platform = await self.stack.enter_async_context(
            AgentPlatform(ME, t, federation=FED, channel=channel)
        )
        # records summing up refusals past the Interface Agent (an agent's not-understood,
        # an unsolicited answer) come on top of its one decision per input, later
        self.summed = 0  # such records, each one call (`AgentPlatform._audit_refusals`)
        self._summed: deque[dict[str, Any]] = deque(maxlen=64)  # the latest of them
        tally = self.platform._refusals
        emit = tally._emit

        def summed(*told: Any) -> None:
            emit(*told)
            self.summed += 1
            self._summed.extend(self.ia.audit.last(1))

        tally._emit = summed
        echo = await self.platform.add(_Echo("echo"))
        assert self.platform.df is not None
        await self.platform.df.register(
            ServiceDescription(
                name="echo-svc", type="demo", provider=echo.aid, visibility="protected"
            )
        )
        # uav-a: its real keys on a plain transport, no platform (its replies go nowhere)
        self.raw: MemoryTransport = await self.stack.enter_async_context(hub.transport())
        self.hs = Handshake(keys(PEER), trust(), policy=BIG_POLICY)
        self.table = SessionTable(PEER, trust(), policy=BIG_POLICY)
        replies = await self.raw.query(
            wire_key(FED, "kx", ME), self.hs.initiate(ME), timeout=self.timeout
        )
        self.table.add(self.hs.finish(replies[0].payload))

        async def respond(key: str, request: bytes) -> bytes | None:
            # uav-b renews its session with uav-a now and then, as with a real peer
            reply, session = self.hs.respond(request)
            self.table.add(session)
            return reply

        await self.raw.serve(wire_key(FED, "kx", PEER), respond)
        self.outbox: Subscription[Message] = await self.raw.subscribe(wire_key(FED, "acl", PEER))
        self.inbox = wire_key(FED, "acl", ME)
        self._inbox_task = next(
            t for t in self.platform._tasks if t.get_name().endswith("interface.inbox")
        )

    def seal(self, body: bytes, *, binary: bool = False) -> bytes:
        """``body`` sealed by uav-a for uav-b (encrypted, its tag right): a JSON envelope,
        or with ``binary`` one in the binary form (a msgpack array)."""
        envelope = self.table.seal_binary(ME, body) if binary else self.table.seal(ME, body)
        if len(self._sealed) > 4096:
            self._sealed.clear()
        # an envelope that opens is one of these, unchanged: the body, without the key
        self._sealed[envelope] = body
        return envelope

    def _alive(self) -> bool:
        agent = self.ia.agent
        return not self._inbox_task.done() and agent is not None and agent.running

    def _read_outbox(self) -> None:
        """Open what uav-b sent to uav-a since last time, and tally its performatives."""
        for payload in self.outbox.inbox.drain():
            _, body = self.table.open(payload.payload)
            for message in _messages(body):
                self.answers[message.performative.value] += 1

    def _decisions(self) -> tuple[int, int, int]:
        """Audit records, envelopes dropped as not authentic, messages over a rate limit."""
        stats = self.platform.stats
        # counters of the platform's rate limiting, where it is there (getattr: optional)
        return (
            sum(self.ia.audit.counts.values()) - self.summed,
            getattr(stats, "unauthenticated", 0),
            getattr(stats, "rate_limited", 0),
        )

    async def _feed(self, payload: bytes, **where: Any) -> str:
        audit = self.ia.audit
        records, unauthentic, limited = self._decisions()
        await self.raw.publish(self.inbox, payload)
        # every input ends in a decision: audited, or counted (garbage beyond the audit's
        # budget for unauthenticated input is counted and summed up later); a batch of
        # messages in one envelope, one decision per message
        expected = _batch_size(self._sealed.get(payload, b""))

        def decided() -> bool:
            now = self._decisions()
            return now[1:] != (unauthentic, limited) or now[0] >= records + expected

        await self._until(decided)
        self._read_outbox()
        now_records, now_unauthentic, now_limited = self._decisions()
        if now_unauthentic > unauthentic:
            self.unauthentic += 1
            return "dropped+counted"
        if now_limited > limited:
            return "rate-limited"
        if now_records != records + expected:
            raise Crash(
                f"{now_records - records} audit records for one authentic input "
                f"({expected} message(s))"
            )
        rec = next(r for r in reversed(audit.records) if r not in self._summed)
        verdict = rec["verdict"]
        if verdict == "refused" and rec["performative"] is None:
            # no message was read: its bytes were refused, and its sender is told why,
            # unless what it sent was itself a failure or not-understood (never answered)
            body = self._sealed.get(payload, b"{}")
            return "dropped+counted" if _never_answered(body) else "not-understood"
        return "dropped+counted" if verdict == "dropped" else str(verdict)

    def request(self, content: Any) -> Any:
        """A legitimate authenticated request from asker@uav-a to echo@uav-b: its answer.

        ``(performative, content)``: ``("inform", {"echo": content})`` when all is well.
        """
        return self.loop.run_until_complete(self._request(content))

    async def _request(self, content: Any) -> Any:
        self._read_outbox()
        message = ACLMessage(
            performative=Performative.REQUEST,
            sender=f"asker@{PEER}",
            receivers=[f"echo@{ME}"],
            content=content,
            ontology="demo",
            protocol="fipa-request",
            conversation_id=f"c-legit-{time.monotonic_ns()}",
            reply_with="r-legit",
        )
        await self.raw.publish(self.inbox, self.seal(message.to_json()))
        async with asyncio.timeout(self.timeout):
            while True:
                payload = await self.outbox.get()
                _, body = self.table.open(payload.payload)
                for answer in _messages(body):
                    self.answers[answer.performative.value] += 1
                    if answer.conversation_id == message.conversation_id:
                        return answer.performative.value, answer.content

    def settle(self) -> None:
        """Wait until uav-a got every not-understood the outcomes promise (bounded)."""

        async def wait() -> None:
            def done() -> bool:
                self._read_outbox()
                return self.answers["not-understood"] >= self.outcomes["not-understood"]

            await self._until(done)

        self.loop.run_until_complete(wait())


def _batch_size(body: bytes) -> int:
    """How many messages an (opened) body holds: a batch's, else one (docs/wire.md)."""
    if body[:1] != b"[" or len(body) > MAX_MESSAGE_BYTES:
        return 1
    try:
        items = orjson.loads(body)
    except orjson.JSONDecodeError:
        return 1
    return len(items) if isinstance(items, list) and 1 <= len(items) <= MAX_BATCH else 1


def _messages(body: bytes) -> list[ACLMessage]:
    """The ACL messages of a body uav-b sealed: one, or a batch of them."""
    if body[:1] != b"[":
        return [ACLMessage.from_json(body)]
    return [ACLMessage.from_parsed(obj) for obj in orjson.loads(body)]


def _never_answered(body: bytes) -> bool:
    """Whether an (opened) envelope's body claims a performative nobody answers."""
    try:
        obj = orjson.loads(body)
    except orjson.JSONDecodeError:
        return False
    performative = obj.get("performative") if isinstance(obj, dict) else None
    return isinstance(performative, str) and performative in ("failure", "not-understood")


# --------------------------------------------------------------------------- import


class ImportTarget(_Target):
    """uav-b's import proxy fed raw stream payloads; uav-a (real keys) seals real batches.

    Outcomes: ``dropped:<reason>`` (the whole payload, counted by reason), ``injected``
    (every sample added), ``partly-injected`` / ``samples-dropped`` (malformed samples
    counted, the rest kept), ``unagreed`` (a label never agreed: counted).
    """

    loggers = ("federation._import", "federation._proxy_base")

    def __init__(self, timeout: float = 5.0) -> None:
        super().__init__(timeout)
        self._legit_batches = 0
        self.loop.run_until_complete(self._open())

    async def _open(self) -> None:
        hub = MemoryHub()
        t = await self.stack.enter_async_context(hub.transport())
        self.instance = await self.stack.enter_async_context(DyKnowInstance(ME))
        self.table_b = SessionTable(ME, trust())
        target = self

        class Probed(TableSessions):
            """Opens with uav-b's table; a non-authentication error is a decoder bug."""

            def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
                try:
                    return super().open_bytes(envelope)
                except AuthenticationError:
                    raise
                except Exception as exc:
                    target._foreign.append(exc)
                    raise

        agreed = {SEM: "fed/uav-a/car5", OTHER_SEM: "fed/uav-a/car6"}
        self.proxy = await self.stack.enter_async_context(
            ImportProxy(
                ME,
                FED,
                t,
                self.instance,
                Probed(self.table_b),
                lambda sender, semantic: agreed.get(semantic) if sender == PEER else None,
            )
        )
        self._receive_task = next(
            task for task in self.proxy._tasks if task.get_name().endswith(".receive")
        )
        self.raw: MemoryTransport = await self.stack.enter_async_context(hub.transport())
        hs_a = Handshake(keys(PEER), trust(), policy=BIG_POLICY)
        hs_b = Handshake(keys(ME), trust())
        self.table = SessionTable(PEER, trust(), policy=BIG_POLICY)
        reply, session_b = hs_b.respond(hs_a.initiate(ME))
        self.table.add(hs_a.finish(reply))
        self.table_b.add(session_b)

    def key(self, sender: str = PEER, label: str = SEM) -> str:
        """The stream key a payload from ``sender`` for ``label`` arrives on."""
        return f"{wire_key(FED, 'stream', ME)}/{sender}/{label}"

    def seal(self, body: bytes) -> bytes:
        """``body`` sealed by uav-a for uav-b, as a binary envelope (its MAC is right)."""
        return self.table.seal_bytes(ME, body)

    def _alive(self) -> bool:
        return not self._receive_task.done()

    def _totals(self) -> dict[str, Any]:
        totals: dict[str, Any] = self.proxy.stats()["totals"]
        return totals

    async def _feed(self, payload: bytes, **where: Any) -> str:
        key = where.get("key") or self.key()
        before = self._totals()

        def progress(t: dict[str, Any]) -> int:
            return int(t["batches"]) + sum(t["dropped_batches"].values())

        await self.raw.publish(key, payload)
        # every payload is counted: as a batch, or as a drop of one whose key is malformed
        await self._until(lambda: progress(self._totals()) > progress(before))
        after = self._totals()
        for reason, n in after["dropped_batches"].items():
            if n > before["dropped_batches"].get(reason, 0):
                return f"dropped:{reason}"
        dropped = sum(after["dropped_samples"].values()) - sum(before["dropped_samples"].values())
        injected = after["injected"] - before["injected"]
        received = after["received"] - before["received"]
        if injected + dropped != received:
            raise Crash(f"{received} samples read, {injected} injected, {dropped} counted dropped")
        unagreed = after["dropped_samples"].get("unagreed", 0) - before["dropped_samples"].get(
            "unagreed", 0
        )
        if unagreed:
            return "unagreed"
        if dropped and injected:
            return "partly-injected"
        if dropped:
            return "samples-dropped"
        return "injected"

    def legit(self, values: list[float]) -> list[Any]:
        """A legitimate sealed batch of ``values`` for the agreed label: the values read back."""
        return self.loop.run_until_complete(self._legit(values))

    async def _legit(self, values: list[float]) -> list[Any]:
        self._legit_batches += 1
        # valid times of their own, so garbage samples injected before cannot mix in
        t0 = 2**62 + self._legit_batches * 1_000_000
        now = self.instance.clock.now()
        body = pack_batch(SEM, [(v, t0 + i, now) for i, v in enumerate(values)])
        label = "fed/uav-a/car5"

        def read() -> list[Any]:
            if not self.instance.has_label(label):
                return []
            return [s.value for s in self.instance.between(label, t0, t0 + len(values)).samples]

        await self.raw.publish(self.key(), self.seal(body))
        await self._until(lambda: len(read()) >= len(values))
        return read()
