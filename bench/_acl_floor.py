"""The floor of an ACL round trip: the design's building blocks alone, none of our code.

``python -m bench._acl_floor [--ours] [--rounds R] [N]``. Two spawned processes, an asker
and a replier, each with one zenoh session (peer mode, loopback TCP, as
``bench/_zenoh_raw.py``) and, where a variant has one, an event loop as `agents.run` makes
it (uvloop unless ``DYKNOW_EVENT_LOOP=asyncio``). Each variant is a request → reply round
trip between them:

- ``get`` (a): raw zenoh ``get`` as ``bench/_zenoh_raw.py`` does it (a blocking ``get``
  with an empty request and default get settings, on a queryable answering a 1-byte
  reply on zenoh's thread): the bench's baseline, the one ``bench.acl`` divides by, not a
  lower bound of a round trip (the ``callback-reply`` variant measured 0.71–0.84x of it);
- ``asyncio-echo`` (b): the request a zenoh put, the reply a put, both sides asyncio: the
  subscriber's callback hands the payload over to the loop as our zenoh transport does
  (append to a queue under a lock, ``call_soon_threadsafe`` only when the reader waits),
  a reader task takes it; the replier's reader puts the reply, the asker's resolves the
  Future the asking coroutine awaits (with a timeout timer, as a request has); payloads
  the size of our sealed request and reply, a sequence number their only content;
- ``asyncio-echo-task``: b, with the replier's reader handing each request to a task of
  its own (an agent's mailbox and loop) that puts the reply;
- ``asyncio-aead``: b with each payload boxed by ChaCha20-Poly1305 behind a fixed binary
  header (what a binary envelope would cost at least);
- ``asyncio-crypto`` (c): b plus the work of our envelope and body on both sides, done as
  plainly as it can be: the ACL message as JSON (orjson) of our request's and reply's
  shape, sealed with ChaCha20-Poly1305 (`cryptography`, as ``agents/_security.py``) into
  a JSON envelope with the box in base64, opened (JSON, canonical base64, AEAD, counter)
  and the body parsed on the other side; no agents, no checks beyond those;
- ``asyncio-binary``: c with the envelope laid out in binary (the box behind a fixed
  header, no JSON envelope, no base64); the bodies JSON as in c;
- ``callback-reply`` (d): b with the replier answering on zenoh's callback thread (no
  loop hop there); the asker as in b;
- ``callback-crypto``: c with the replier's work (open, parse, compose, seal, put) on
  zenoh's callback thread;
- ``callback-binary``: both: the binary envelope, the replier's work on zenoh's thread;
- ``asyncio-query`` (e): the request a zenoh ``get`` with the request as its payload,
  answered through the replier's loop (the queryable's callback hands the query over as
  in b), the reply handed over to the asker's loop as in b (the reply callback a
  ``zenoh.handlers.Callback``, zenoh's default ``indirect=True``);
- ``asyncio-query-direct``: e with the asker's reply callback ``indirect=False``, called
  on zenoh's network thread, as our transport's ``ask`` does (with Python's switch
  interval; see ``bench/_ask_threads.py``): with ``indirect=True`` zenoh starts a Python
  thread for each handler, so each ``get`` with a callback starts one (200 gets, 200
  threads; a subscriber's or queryable's handler is one thread for its life).

The variants take turns in blocks of ``BLOCK`` round trips (a cycle: a block of each,
forward, then backward, ...), so that all meet the same load on a shared machine; a
round is ``N // BLOCK`` cycles. ``--ours`` adds our whole stack's round trip as one more
turn of each cycle (``request`` to the gateway of a spawned node as ``bench.acl`` and
``bench._acl_cpu`` run it: two platforms, the Interface Agent, encryption on; its asker
in this process).

Printed per variant: round trip median and p99 (µs, all rounds pooled), the CPU per round
trip (µs, median of the rounds) of each side's loop thread (its main thread: where a
blocking ``get`` waits in a) and of all its threads (zenoh's included; from
``/proc/<pid>/task/*/schedstat``, as ``bench._acl_cpu``), the median's ratio to a's, and
each round's median (their spread says how noisy the run was); and the ratios as ``BENCH
acl-floor-<variant>-vs-get`` lines, whose ``ours=`` holds the floor variant's median (ms,
``ours`` too for our stack's) and ``zenoh-get=`` a's. CPU per round trip depends little on
what else loads the machine; the round trips do.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import gc
import os
import statistics
import struct
import sys
import tempfile
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

from bench import progress, report
from bench._acl_cpu import _all_threads_cpu, _main_thread_cpu
from bench._child import Child
from bench._zenoh_raw import _config, free_port

N_RTT = 2000
WARMUP = 300
ROUNDS = 3
BLOCK = 100  # round trips of one variant before the next one's
TIMEOUT = 5.0  # a request's reply timeout, as bench.acl's
REQ_BYTES = 553  # our sealed request to the gateway (bench.acl's round trip), on the wire
REP_BYTES = 585  # and its sealed reply
VARIANTS = {
    "get": "a. raw zenoh get, answered on zenoh's thread",
    "asyncio-echo": "b. put/sub both ways, each side's loop",
    "asyncio-echo-task": "b + replier's answer in its own task",
    "asyncio-aead": "b + AEAD of binary bodies only",
    "asyncio-crypto": "c. b + seal/open + JSON bodies",
    "asyncio-binary": "c with a binary envelope",
    "callback-reply": "d. b, replier answers on zenoh's thread",
    "callback-crypto": "c, replier works on zenoh's thread",
    "callback-binary": "both of the two above",
    "asyncio-query": "e. get/queryable, each side's loop",
    "asyncio-query-direct": "e, asker's reply callback direct",
}
SID = "Ano7Hijzn7f3C4ynN7Xojw"  # a session id of our length
KEYS = (bytes(range(32)), bytes(range(32, 64)))  # the asker→replier and replier→asker keys
_SEQ = struct.Struct("<Q")
_NONCE = struct.Struct(">IQ")
_U64X2 = struct.Struct(">QQ")
_ENV_FIELDS = frozenset({"v", "from", "to", "sid", "ts_ms", "n", "box"})


class _Box:
    """A transport inbox's mechanism, per item: a deque under a lock, the loop woken only
    when its one reader waits (``call_soon_threadsafe``); ``put`` from any thread."""

    __slots__ = ("_items", "_lock", "_loop", "_waiter", "_wake_pending")

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._items: deque[Any] = deque()
        self._lock = threading.Lock()
        self._waiter: asyncio.Future[None] | None = None
        self._wake_pending = False

    def put(self, item: Any) -> None:
        """Queue ``item``; wake the reader if it waits and no wake-up is pending."""
        with self._lock:
            self._items.append(item)
            if self._waiter is None or self._wake_pending:
                return
            self._wake_pending = True
        self._loop.call_soon_threadsafe(self._wake)

    def _wake(self) -> None:
        with self._lock:
            self._wake_pending = False
            w, self._waiter = self._waiter, None
        if w is not None and not w.done():
            w.set_result(None)

    async def get(self) -> Any:
        """The next item (on the loop's thread)."""
        while True:
            with self._lock:
                if self._items:
                    return self._items.popleft()
                w = self._waiter = self._loop.create_future()
            await w


class _Mailbox:
    """An agent's mailbox within the loop: put and get on the loop's thread only."""

    __slots__ = ("_items", "_loop", "_waiter")

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._items: deque[Any] = deque()
        self._waiter: asyncio.Future[None] | None = None

    def put(self, item: Any) -> None:
        """Queue ``item`` and wake the waiting task."""
        self._items.append(item)
        w, self._waiter = self._waiter, None
        if w is not None and not w.done():
            w.set_result(None)

    async def get(self) -> Any:
        """The next item."""
        while not self._items:
            w = self._waiter = self._loop.create_future()
            await w
        return self._items.popleft()


def _b64() -> tuple[Callable[[bytes], bytes], Callable[[str], bytes]]:
    """Encode and canonical-decode base64 as our envelope does (pybase64 where installed)."""
    try:
        import pybase64

        enc: Callable[[bytes], bytes] = pybase64.b64encode

        def dec(text: str) -> bytes:
            raw: bytes = pybase64.b64decode(text, validate=True)
            if enc(raw) != text.encode():
                raise ValueError("not canonical base64")
            return raw

    except ImportError:
        import binascii

        def enc(raw: bytes) -> bytes:
            return binascii.b2a_base64(raw, newline=False)

        def dec(text: str) -> bytes:
            raw = binascii.a2b_base64(text, strict_mode=True)
            if enc(raw) != text.encode():
                raise ValueError("not canonical base64")
            return raw

    return enc, dec


class _Envelopes:
    """One session's sealing and opening, in JSON envelopes like ours, with nothing else."""

    def __init__(self, me: str, peer: str, tx: bytes, rx: bytes) -> None:
        import orjson
        from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305

        self._seal = ChaCha20Poly1305(tx).encrypt
        self._open = ChaCha20Poly1305(rx).decrypt
        self._loads = orjson.loads
        self._enc, self._dec = _b64()
        head = {"v": 1, "from": me, "to": peer, "sid": SID, "ts_ms": 0}
        self._prefix = orjson.dumps(head)[:-2]
        self._ad_tx = f"dyknow-acl\0{me}\0{peer}\0{SID}".encode()
        self._ad_rx = f"dyknow-acl\0{peer}\0{me}\0{SID}".encode()
        self._n = 0
        self._hi = 0

    def seal(self, body: bytes) -> bytes:
        """``body`` boxed into an envelope for the peer."""
        n = self._n = self._n + 1
        ts = int(time.time() * 1000)
        box = self._seal(_NONCE.pack(0, n), body, self._ad_tx + _U64X2.pack(ts, n))
        return b'%b%d,"n":%d,"box":"%b"}' % (self._prefix, ts, n, self._enc(box))

    def open(self, envelope: bytes) -> bytes:
        """The body of the peer's ``envelope``; ValueError (or InvalidTag) when refused."""
        env = self._loads(envelope)
        if type(env) is not dict or env.keys() != _ENV_FIELDS:
            raise ValueError("not an envelope")
        ts, n, box = env["ts_ms"], env["n"], env["box"]
        if type(ts) is not int or type(n) is not int or type(box) is not str:
            raise ValueError("bad field types")
        body: bytes = self._open(
            _NONCE.pack(0, n), self._dec(box), self._ad_rx + _U64X2.pack(ts, n)
        )
        if n <= self._hi:
            raise ValueError("replayed")
        self._hi = n
        return body


class _BinaryBoxes:
    """AEAD alone: ``seq, ts, n`` in a fixed header (authenticated), the body boxed after it."""

    HEADER = struct.Struct("<QQQ")

    def __init__(self, tx: bytes, rx: bytes) -> None:
        from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305

        self._seal = ChaCha20Poly1305(tx).encrypt
        self._open = ChaCha20Poly1305(rx).decrypt
        self._n = 0
        self._hi = 0

    def seal(self, seq: int, body: bytes) -> bytes:
        """``body`` boxed after its header, conversation ``seq``."""
        n = self._n = self._n + 1
        head = self.HEADER.pack(seq, int(time.time() * 1000), n)
        return head + self._seal(_NONCE.pack(0, n), body, head)

    def open(self, data: bytes) -> tuple[int, bytes]:
        """``(seq, body)`` of the peer's ``data``; ValueError (or InvalidTag) when refused."""
        head = data[: self.HEADER.size]
        seq, _ts, n = self.HEADER.unpack(head)
        body: bytes = self._open(_NONCE.pack(0, n), data[self.HEADER.size :], head)
        if n <= self._hi:
            raise ValueError("replayed")
        self._hi = n
        return seq, body


class _BinaryEnvelopes:
    """Our envelope's work laid out in binary: the AEAD box behind a fixed header (no JSON
    envelope, no base64), the body still the ACL message's JSON."""

    def __init__(self, tx: bytes, rx: bytes) -> None:
        self._boxes = _BinaryBoxes(tx, rx)

    def seal(self, body: bytes) -> bytes:
        """``body`` boxed for the peer."""
        return self._boxes.seal(0, body)

    def open(self, data: bytes) -> bytes:
        """The body of the peer's ``data``; ValueError (or InvalidTag) when refused."""
        return self._boxes.open(data)[1]


# what a binary body holds so that header and tag make a payload of our sealed sizes
_AEAD_OVERHEAD = _BinaryBoxes.HEADER.size + 16


def _request_body(i: int) -> dict[str, Any]:
    """An ACL request of our round trip's shape, conversation ``i``."""
    return {
        "v": 1,
        "performative": "request",
        "sender": "asker@bench-a",
        "receivers": ["gateway@bench-b"],
        "content": {"action": "query", "label": "bench/speed", "kind": "latest"},
        "language": "json",
        "ontology": "dyknow",
        "protocol": "fipa-request",
        "conversation_id": f"c-da7bfa7f-{i}",
        "reply_with": f"r-da7bfa7f-{i}",
        "reply_by": time.time() + TIMEOUT,
    }


def _reply_body(req: dict[str, Any]) -> dict[str, Any]:
    """The gateway's inform of our round trip's shape, answering ``req``."""
    now = time.time()
    return {
        "v": 1,
        "performative": "inform",
        "sender": req["receivers"][0],
        "receivers": [req["sender"]],
        "content": {"label": "bench/speed", "query_time": now, "samples": [[13.1, now, now]]},
        "language": "json",
        "ontology": "dyknow",
        "protocol": "fipa-request",
        "conversation_id": req["conversation_id"],
        "in_reply_to": req["reply_with"],
    }


def _pad(n: int) -> bytes:
    return b"x" * (n - _SEQ.size)


def _publisher(session: Any, key: str) -> Any:
    import zenoh

    # as our transport declares its publishers
    return session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.DROP, reliability=zenoh.Reliability.RELIABLE
    )


# --------------------------------------------------------------------------- replier


def replier_main(port: int, reports: Any, stop: Any) -> None:
    """The answering process: every variant's replier, until ``stop``."""
    try:
        from agents import run

        run(_replier(port, reports, stop))
    except BaseException:
        reports.put(("error", os.getpid(), traceback.format_exc()))
        raise


async def _replier(port: int, reports: Any, stop: Any) -> None:
    import orjson
    import zenoh

    loop = asyncio.get_running_loop()
    reply_pad = _pad(REP_BYTES)
    seq = _SEQ.size
    with zenoh.open(_config([f"tcp/127.0.0.1:{port}"], [])) as s:
        held: list[Any] = [s.declare_queryable("floor/get", lambda q: q.reply(q.key_expr, b"x"))]
        tasks: list[asyncio.Task[None]] = []

        def boxed(key: str) -> _Box:
            box = _Box(loop)
            put = box.put
            held.append(s.declare_subscriber(key, lambda smp: put(smp.payload.to_bytes())))
            return box

        async def echo(box: _Box, pub: Any) -> None:
            while True:
                payload = await box.get()
                pub.put(payload[:seq] + reply_pad)

        async def echo_via_task(box: _Box, pub: Any) -> None:
            mailbox = _Mailbox(loop)

            async def agent() -> None:
                while True:
                    payload = await mailbox.get()
                    pub.put(payload[:seq] + reply_pad)

            tasks.append(loop.create_task(agent()))
            while True:
                mailbox.put(await box.get())

        def answerer(pub: Any, binary: bool = False) -> Callable[[bytes], None]:
            # a session of its own for each variant: counters and replay windows apart
            env: _Envelopes | _BinaryEnvelopes = (
                _BinaryEnvelopes(KEYS[1], KEYS[0])
                if binary
                else _Envelopes("bench-b", "bench-a", KEYS[1], KEYS[0])
            )
            loads, dumps, put = orjson.loads, orjson.dumps, pub.put

            def answer(payload: bytes) -> None:
                req = loads(env.open(payload))
                if type(req) is dict and req.get("performative") == "request":
                    put(env.seal(dumps(_reply_body(req))))

            return answer

        async def crypto(box: _Box, pub: Any) -> None:
            answer = answerer(pub)
            while True:
                answer(await box.get())

        async def binary(box: _Box, pub: Any) -> None:
            answer = answerer(pub, binary=True)
            while True:
                answer(await box.get())

        async def aead(box: _Box, pub: Any) -> None:
            boxes = _BinaryBoxes(KEYS[1], KEYS[0])
            body = b"y" * (REP_BYTES - _AEAD_OVERHEAD)
            while True:
                i, _ = boxes.open(await box.get())
                pub.put(boxes.seal(i, body))

        async def query(box: _Box) -> None:
            while True:
                q = await box.get()
                body = q.payload
                q.reply("floor/query", (b"" if body is None else body.to_bytes())[:seq] + reply_pad)
                q.drop()

        for name, serve in (
            ("asyncio-echo", echo),
            ("asyncio-echo-task", echo_via_task),
            ("asyncio-crypto", crypto),
            ("asyncio-binary", binary),
            ("asyncio-aead", aead),
        ):
            box = boxed(f"floor/{name}/req")
            tasks.append(loop.create_task(serve(box, _publisher(s, f"floor/{name}/rep"))))
        direct = _publisher(s, "floor/callback-reply/rep")
        held.append(
            s.declare_subscriber(
                "floor/callback-reply/req",
                lambda smp: direct.put(smp.payload.to_bytes()[:seq] + reply_pad),
            )
        )
        for name, binary_env in (("callback-crypto", False), ("callback-binary", True)):
            answer = answerer(_publisher(s, f"floor/{name}/rep"), binary_env)
            held.append(
                s.declare_subscriber(
                    f"floor/{name}/req",
                    functools.partial(_answer_sample, answer),
                )
            )
        qbox = _Box(loop)
        held.append(s.declare_queryable("floor/query", qbox.put))
        tasks.append(loop.create_task(query(qbox)))
        gc.collect()
        gc.freeze()
        reports.put(("ready", os.getpid(), None))
        await loop.run_in_executor(None, stop.wait)
        for t in tasks:
            t.cancel()
        for h in held:
            h.undeclare()


# --------------------------------------------------------------------------- asker


def asker_main(port: int, replier: int, commands: Any, reports: Any, stop: Any) -> None:
    """The asking process: on each command ``(order, n, warmup)``, one round of every variant."""
    try:
        from agents import event_loop_name, run

        reports.put(("loop", os.getpid(), event_loop_name()))
        run(_asker(port, replier, commands, reports, stop))
    except BaseException:
        reports.put(("error", os.getpid(), traceback.format_exc()))
        raise


Ask = Callable[[int], Coroutine[Any, Any, Any]]


async def _asker(port: int, replier: int, commands: Any, reports: Any, stop: Any) -> None:
    import orjson
    import zenoh

    loop = asyncio.get_running_loop()
    request_pad = _pad(REQ_BYTES)
    unpack = _SEQ.unpack_from
    with zenoh.open(_config([], [f"tcp/127.0.0.1:{port}"])) as s:
        held: list[Any] = []
        tasks: list[asyncio.Task[None]] = []
        asks: dict[str, Ask] = {}

        async def get(i: int) -> Any:
            # blocking, as bench/_zenoh_raw.py: the loop waits with it
            replies = list(s.get("floor/get", timeout=2.0))
            if not replies or replies[0].ok is None:
                raise RuntimeError("raw get unanswered")
            return replies

        asks["get"] = get

        def expire(fut: asyncio.Future[Any]) -> None:
            if not fut.done():
                fut.set_exception(TimeoutError("no reply"))

        async def read_seq(box: _Box, pending: dict[int, asyncio.Future[Any]]) -> None:
            while True:
                payload = await box.get()
                fut = pending.pop(unpack(payload)[0], None)
                if fut is not None and not fut.done():
                    fut.set_result(payload)

        def put_asker(name: str) -> Ask:
            box = _Box(loop)
            put = box.put
            held.append(
                s.declare_subscriber(f"floor/{name}/rep", lambda smp: put(smp.payload.to_bytes()))
            )
            pending: dict[int, asyncio.Future[Any]] = {}
            tasks.append(loop.create_task(read_seq(box, pending)))
            pub = _publisher(s, f"floor/{name}/req")

            async def ask(i: int) -> Any:
                fut = pending[i] = loop.create_future()
                timer = loop.call_later(TIMEOUT, expire, fut)
                try:
                    pub.put(_SEQ.pack(i) + request_pad)
                    return await fut
                finally:
                    timer.cancel()
                    pending.pop(i, None)

            return ask

        for name in ("asyncio-echo", "asyncio-echo-task", "callback-reply"):
            asks[name] = put_asker(name)

        def crypto_asker(name: str, binary: bool = False) -> Ask:
            # c: our envelope's and body's work, plainly
            env: _Envelopes | _BinaryEnvelopes = (
                _BinaryEnvelopes(KEYS[0], KEYS[1])
                if binary
                else _Envelopes("bench-a", "bench-b", KEYS[0], KEYS[1])
            )
            box = _Box(loop)
            put = box.put
            held.append(
                s.declare_subscriber(f"floor/{name}/rep", lambda smp: put(smp.payload.to_bytes()))
            )
            pending: dict[Any, asyncio.Future[Any]] = {}
            pub = _publisher(s, f"floor/{name}/req")
            loads, dumps = orjson.loads, orjson.dumps

            async def read() -> None:
                while True:
                    msg = loads(env.open(await box.get()))
                    if type(msg) is not dict:
                        continue
                    fut = pending.pop(msg.get("in_reply_to"), None)
                    if fut is not None and not fut.done():
                        fut.set_result(msg["content"])

            tasks.append(loop.create_task(read()))

            async def ask(i: int) -> Any:
                body = _request_body(i)
                key = body["reply_with"]
                fut = pending[key] = loop.create_future()
                timer = loop.call_later(TIMEOUT, expire, fut)
                try:
                    pub.put(env.seal(dumps(body)))
                    return await fut
                finally:
                    timer.cancel()
                    pending.pop(key, None)

            return ask

        for name in ("asyncio-crypto", "callback-crypto"):
            asks[name] = crypto_asker(name)
        for name in ("asyncio-binary", "callback-binary"):
            asks[name] = crypto_asker(name, binary=True)

        # AEAD alone, binary
        boxes = _BinaryBoxes(KEYS[0], KEYS[1])
        abox = _Box(loop)
        aput = abox.put
        held.append(
            s.declare_subscriber("floor/asyncio-aead/rep", lambda smp: aput(smp.payload.to_bytes()))
        )
        apending: dict[int, asyncio.Future[Any]] = {}
        apub = _publisher(s, "floor/asyncio-aead/req")
        abody = b"x" * (REQ_BYTES - _AEAD_OVERHEAD)

        async def read_aead() -> None:
            while True:
                i, body = boxes.open(await abox.get())
                fut = apending.pop(i, None)
                if fut is not None and not fut.done():
                    fut.set_result(body)

        tasks.append(loop.create_task(read_aead()))

        async def ask_aead(i: int) -> Any:
            fut = apending[i] = loop.create_future()
            timer = loop.call_later(TIMEOUT, expire, fut)
            try:
                apub.put(boxes.seal(i, abody))
                return await fut
            finally:
                timer.cancel()
                apending.pop(i, None)

        asks["asyncio-aead"] = ask_aead

        # e: a query per request, the reply handed over to the loop
        qbox = _Box(loop)
        qput = qbox.put
        qpending: dict[int, asyncio.Future[Any]] = {}
        tasks.append(loop.create_task(read_seq(qbox, qpending)))

        def on_reply(reply: Any) -> None:
            ok = reply.ok
            if ok is not None:
                qput(ok.payload.to_bytes())

        def query_asker(indirect: bool) -> Ask:
            async def ask(i: int) -> Any:
                fut = qpending[i] = loop.create_future()
                timer = loop.call_later(TIMEOUT, expire, fut)
                try:
                    s.get(
                        "floor/query",
                        zenoh.handlers.Callback(on_reply, _nothing, indirect=indirect),
                        payload=_SEQ.pack(i) + request_pad,
                        timeout=2.0,
                        target=zenoh.QueryTarget.ALL,
                        consolidation=zenoh.ConsolidationMode.NONE,
                    )
                    return await fut
                finally:
                    timer.cancel()
                    qpending.pop(i, None)

            return ask

        asks["asyncio-query"] = query_asker(True)
        asks["asyncio-query-direct"] = query_asker(False)

        await _first_answers(asks)
        reports.put(("ready", os.getpid(), None))
        me = os.getpid()
        while True:
            cmd = await loop.run_in_executor(None, commands.get)
            if cmd is None:
                break
            what, order, n = cmd
            out: dict[str, Any] = {}
            for name in order:
                if what == "warm-up":
                    for i in range(n):
                        await asks[name](i)
                else:
                    out[name] = await _timed(asks[name], n, me, replier)
            if what == "warm-up":
                gc.collect()
                gc.freeze()
            reports.put((what, me, out))
        for t in tasks:
            t.cancel()
        for h in held:
            h.undeclare()


def _answer_sample(answer: Callable[[bytes], None], sample: Any) -> None:
    answer(sample.payload.to_bytes())


def _nothing() -> None:
    pass


async def _first_answers(asks: dict[str, Ask]) -> None:
    """Until every variant answers once (declarations take a moment to reach the peer)."""
    deadline = time.monotonic() + 30.0
    for name, ask in asks.items():
        while True:
            try:
                await asyncio.wait_for(ask(0), 1.0)
                break
            except (TimeoutError, RuntimeError):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"floor variant {name} never answered") from None


async def _timed(ask: Ask, n: int, me: int, other: int) -> tuple[list[float], list[float]]:
    """``n`` round trips of ``ask``, each in µs; the CPU (µs) they took: this process's
    loop thread and all its threads, ``other``'s (the replier's) the same."""
    ns = time.perf_counter_ns
    before = _cpu(me, other)
    rtts = []
    for i in range(n):
        t = ns()
        await ask(i)
        rtts.append((ns() - t) / 1e3)
    return rtts, [(b - a) * 1e6 for a, b in zip(before, _cpu(me, other), strict=True)]


def _cpu(me: int, other: int) -> tuple[float, float, float, float]:
    """The CPU seconds of ``me``'s main (loop) thread and all its threads, ``other``'s too."""
    return (
        _main_thread_cpu(me),
        _all_threads_cpu(me),
        _main_thread_cpu(other),
        _all_threads_cpu(other),
    )


# --------------------------------------------------------------------------- parent


def measure(
    n: int = N_RTT,
    rounds: int = ROUNDS,
    *,
    block: int = BLOCK,
    warmup: int = WARMUP,
    ours: bool = False,
) -> dict[str, Any]:
    """Every variant's round trips, ``n`` a round, in blocks interleaved; with ``ours``, ours.

    Each round is ``n // block`` cycles; a cycle runs ``block`` round trips of each
    variant (and of ours), forward and backward in turn, so that all see the same load.
    Per round and variant: the round trips (µs) and the CPU per round trip (µs).
    """
    from agents import run

    return run(_measure(n, rounds, block, warmup, ours))


async def _measure(n: int, rounds: int, block: int, warmup: int, ours: bool) -> dict[str, Any]:
    from bench._child import _CTX

    port = free_port()
    commands = _CTX.Queue()
    names = list(VARIANTS)
    res: dict[str, Any] = {name: [] for name in [*names, *(["ours"] if ours else [])]}
    async with contextlib.AsyncExitStack() as stack:
        replier = stack.enter_context(Child(replier_main, (port,), "floor-replier").start())
        await asyncio.to_thread(replier.wait_report, "ready", 30.0)
        args = (port, replier.pid, commands)
        asker = stack.enter_context(Child(asker_main, args, "floor-asker").start())
        res["loop"] = await asyncio.to_thread(asker.wait_report, "loop", 30.0)
        await asyncio.to_thread(asker.wait_report, "ready", 60.0)
        ask_ours: Callable[[], Coroutine[Any, Any, tuple[list[float], list[float]]]] | None = None
        if ours:
            ask_ours = await _our_stack(stack, block, warmup)
        progress(f"floor: warm-up, {warmup} round trips of each variant")
        commands.put(("warm-up", names, warmup))
        await asyncio.to_thread(asker.wait_report, "warm-up", 120.0)
        cycles = max(1, n // block)
        for r in range(rounds):
            progress(f"floor round {r + 1}/{rounds}: {cycles} cycles of {block} round trips each")
            acc: dict[str, tuple[list[float], list[float]]] = {}
            for c in range(cycles):
                forward = c % 2 == 0
                if ask_ours is not None and forward:
                    _add(acc, "ours", await ask_ours())
                commands.put(("cycle", names if forward else names[::-1], block))
                got = await asyncio.to_thread(asker.wait_report, "cycle", 60.0 + block * 0.1)
                for name, one in got.items():
                    _add(acc, name, one)
                if ask_ours is not None and not forward:
                    _add(acc, "ours", await ask_ours())
            for name, (rtts, cpu) in acc.items():
                per = [x / len(rtts) for x in cpu]
                res[name].append(
                    {
                        "rtts": rtts,
                        "loop_a": per[0],
                        "all_a": per[1],
                        "loop_b": per[2],
                        "all_b": per[3],
                    }
                )
        commands.put(None)
    return res


def _add(
    acc: dict[str, tuple[list[float], list[float]]], name: str, one: tuple[list[float], list[float]]
) -> None:
    rtts, cpu = acc.setdefault(name, ([], [0.0, 0.0, 0.0, 0.0]))
    rtts.extend(one[0])
    for i, x in enumerate(one[1]):
        cpu[i] += x


async def _our_stack(
    stack: contextlib.AsyncExitStack, block: int, warmup: int
) -> Callable[[], Coroutine[Any, Any, tuple[list[float], list[float]]]]:
    """Our whole stack's round trip, as ``bench._acl_cpu`` runs it, ready for timed blocks."""
    from agents import request
    from bench import acl

    keydir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-floor-")))
    acl.make_keys(keydir)
    _, _, asker, presence, config = await stack.enter_async_context(acl.asker_side(keydir))
    child = acl.node("zenoh", config, keydir).start()
    stack.push_async_callback(asyncio.to_thread, child.close)
    await acl.wait_alive(presence, child, True)
    await acl.first_reply(asker, child)
    progress(f"floor: our stack, warm-up ({warmup} round trips)")
    await acl.round_trips(asker, warmup, "warm-up")
    acl.settle_gc()
    me, node = os.getpid(), child.pid

    async def ask(i: int) -> Any:
        return await request(asker, acl.GATEWAY, acl.QUERY, ontology="dyknow", timeout=TIMEOUT)

    return lambda: _timed(ask, block, me, node)


def summarise(res: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per variant: median and p99 of all round trips (µs), median CPU per round trip."""
    out: dict[str, dict[str, Any]] = {}
    for name in [*VARIANTS, *(["ours"] if res.get("ours") else [])]:
        rounds = res[name]
        rtts = sorted(x for r in rounds for x in r["rtts"])
        row = {
            "median": statistics.median(rtts),
            "p99": rtts[min(len(rtts) - 1, int(0.99 * len(rtts)))],
            "round_medians": [statistics.median(r["rtts"]) for r in rounds],
        }
        for k in ("loop_a", "all_a", "loop_b", "all_b"):
            row[k] = statistics.median(r[k] for r in rounds)
        out[name] = row
    return out


def print_floor(res: dict[str, Any]) -> list[str]:
    """Print the table and the BENCH lines (returned)."""
    rows = summarise(res)
    base = rows["get"]["median"]
    print(
        f"  acl floor ({res.get('loop', '?')}; µs per round trip; CPU: loop thread / all threads)"
    )
    print(
        f"  {'variant':<20} {'median':>7} {'p99':>7}  {'asker CPU':>11}  {'replier CPU':>11}"
        f"  {'x get':>5}  rounds' medians"
    )
    for name, row in rows.items():
        meds = " ".join(f"{m:.0f}" for m in row["round_medians"])
        print(
            f"  {name:<20} {row['median']:7.1f} {row['p99']:7.1f}  "
            f"{row['loop_a']:5.1f}/{row['all_a']:5.1f}  {row['loop_b']:5.1f}/{row['all_b']:5.1f}"
            f"  {row['median'] / base:5.2f}  {meds}"
        )
    return [
        report(
            f"acl-floor-{name}-vs-get",
            row["median"] / 1e3,
            "zenoh-get",
            base / 1e3,
            "ms",
            better="lower",
        )
        for name, row in rows.items()
        if name != "get"
    ]


def main(argv: list[str]) -> None:
    """Parse the command line (see the module's docstring), measure, print."""
    ours = "--ours" in argv
    args = [a for a in argv if a != "--ours"]
    rounds = ROUNDS
    if args[:1] == ["--rounds"]:
        rounds, args = int(args[1]), args[2:]
    n = int(args[0]) if args else N_RTT
    print_floor(measure(n, rounds, ours=ours))


if __name__ == "__main__":
    from bench import helped

    if not helped(sys.argv[1:], __doc__):
        main(sys.argv[1:])
