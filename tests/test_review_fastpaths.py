"""The fast paths decide as the checks they stand in for: each is attacked against its oracle.

An envelope's base64 box against the old canonical check (re-encode the whole box and
compare); a reply made without `build` against `build`.
"""

from __future__ import annotations

import asyncio
import binascii
import contextlib
import string
import time
from pathlib import Path
from typing import Any

import orjson
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agents import ACLMessage, MessageError, RateLimit, wire_key
from agents import Performative as P
from agents._exceptions import Expired
from agents._security import _box_bytes, _box_bytes_std, _box_text
from agents.transports import MemoryHub, MemoryTransport
from federation._sessions import PlainSessions

FED = "demo"

# -- the envelope's box: canonical base64 only ------------------------------------------


def _old_canonical(payload: str) -> bool:
    """The check before the rewrite: decode leniently, re-encode it all, compare."""
    try:
        raw = binascii.a2b_base64(payload)
    except ValueError:
        raw = b""
    return bool(raw) and binascii.b2a_base64(raw, newline=False) == payload.encode()


def _new_canonical(payload: str) -> bool:
    """The check `Session._accept` makes now, both ways it is made: each must say the same.

    binascii's (strict decoding, the length, the last quantum), and the one in use (SIMD
    base64 where installed: its decoding, the whole box encoded again and compared).
    """
    std, used = _box_bytes_std(payload), _box_bytes(payload)
    assert std == used, repr(payload)
    return bool(used)


_B64 = string.ascii_letters + string.digits + "+/"
# the alphabet, padding, the url-safe letters, whitespace, and a few that are none of them
_HOSTILE = _B64 + "=-_ \n\r\t.\x00é"


def _spellings(raw: bytes) -> list[str]:
    """The canonical spelling of ``raw`` and near ones: other tail bits, padding, spaces."""
    good = binascii.b2a_base64(raw, newline=False).decode("ascii")
    out = [good, good.rstrip("="), good + "=", good + "==", " " + good, good + "\n"]
    out += [good[:i] + "\n" + good[i:] for i in range(0, len(good), 5)]
    out.append(good.replace("+", "-").replace("/", "_"))
    stripped = good.rstrip("=")
    if stripped:
        # every letter in the last position: the unused bits set in all ways
        out += [stripped[:-1] + c + good[len(stripped) :] for c in _B64]
    return out


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=40))
def test_the_box_check_accepts_what_the_old_one_did_near_a_canonical_spelling(
    raw: bytes,
) -> None:
    for text in _spellings(raw):
        assert _new_canonical(text) == _old_canonical(text), repr(text)


@settings(max_examples=2000, deadline=None)
@given(st.text(alphabet=_HOSTILE, max_size=24))
def test_the_box_check_accepts_what_the_old_one_did_for_any_text(text: str) -> None:
    assert _new_canonical(text) == _old_canonical(text), repr(text)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=3000))
def test_the_box_is_spelled_as_binascii_spells_it(raw: bytes) -> None:
    assert _box_text(raw) == binascii.b2a_base64(raw, newline=False)


@pytest.mark.parametrize(
    "text", ["", "=", "====", "QQ", "QQ=", "QR==", "QQ===", "QQ==QQ==", "QUI=", "QUJD", " QUJD"]
)
def test_the_box_check_on_the_known_edge_cases(text: str) -> None:
    assert _new_canonical(text) == _old_canonical(text)


# -- ACLMessage.reply: what build would make, or build's error ------------------------------


def _asked() -> ACLMessage:
    return ACLMessage.build(
        performative=P.REQUEST,
        sender="a@p1",
        receivers=["b@p2"],
        content={"x": 1},
        conversation_id="c-1",
        reply_with="r-1",
        protocol="fipa-request",
        ontology="o",
        language="json",
    )


class _Lying(str):
    """A str that says it equals (and hashes as) an identifier it does not spell."""

    def __eq__(self, other: object) -> bool:
        return True

    def __hash__(self) -> int:
        return hash("b@p2")


@pytest.mark.parametrize("sender", [["b@p2"], {"b": 1}, _Lying("not an aid")])
def test_a_reply_from_a_sender_that_is_no_identifier_is_refused_as_build_refuses(
    sender: object,
) -> None:
    asked = _asked()
    ACLMessage.build(performative=P.INFORM, sender="b@p2", receivers=["a@p1"])  # known now
    with pytest.raises((MessageError, ValueError)) as built:
        ACLMessage.build(
            performative=P.INFORM,
            sender=sender,
            receivers=["a@p1"],
        )
    with pytest.raises(type(built.value)):
        asked.reply(P.INFORM, {"ok": True}, sender=sender)  # type: ignore[arg-type]


def test_a_reply_is_the_message_build_makes() -> None:
    asked = _asked()
    for content in (None, 1, 1.5, "s", [1, [2, {"a": None}]], {"k": [True, {"z": "y"}]}):
        got = asked.reply(P.INFORM, content)
        want = ACLMessage.build(
            performative=P.INFORM,
            sender="b@p2",
            receivers=["a@p1"],
            content=content,
            language="json",
            ontology="o",
            protocol="fipa-request",
            conversation_id="c-1",
            in_reply_to="r-1",
        )
        assert got == want
        assert got.model_fields_set == want.model_fields_set
        assert got.to_json() == want.to_json()


# -- InterfaceAgent: a batch's messages decided as each alone -------------------------------


async def _decisions(batched: bool, runs: bool = False) -> dict[str, Any]:
    """What uav-b decides about one hostile mix of messages from uav-a, batched or one by one.

    With ``runs``: runs of messages for two agents from two senders, interleaved, with a
    forged sender or receiver in the middle of a run (the batch path caches both).
    """
    from test_interface import Listener, _captured_session, federation, ia, serve, until

    async with federation("uav-a", "uav-b") as fed:
        limit = RateLimit(rate=1e-3, burst=4.0, total_rate=1e-3, total_burst=14.0, refusals=1e-3)
        pair = await _captured_session(fed)
        pa, pb = pair.pa, pair.pb
        # a fresh sender state with these limits (the captured request used the default one)
        ib = ia(pb)
        ib.rate_limit = limit
        ib._senders.clear()
        await pa.add(Listener("l"))
        await serve(pb, "private", None)
        stopped = await serve(pb, "stopped")
        await stopped.stop()
        echo = pair.echo
        echo.calls.clear()
        echo.informs.clear()
        inform, req = P.INFORM, P.REQUEST
        items: list[Any] = [
            _m("l@uav-a", "echo@uav-b", inform, {"i": 1}),
            _m("l@uav-a", "echo@uav-b", req, {"i": 2}),
            _m("l@uav-a", "private@uav-b", req, {"i": 3}),  # no service: refused
            _m("victim@uav-c", "echo@uav-b", inform, {"i": 4}),  # forged sender
            _m("l@uav-a", "echo@uav-b", req, {"i": 5}, reply_to=["x@uav-c"]),  # reflection
            _m("l@uav-a", "echo@uav-b", inform, {"i": 6}, reply_to=["echo@uav-b"]),
            _m("l@uav-a", "ghost@uav-b", inform, {"i": 7}),  # no such agent
            _m("l@uav-a", "stopped@uav-b", inform, {"i": 8}),  # stopped
            {"performative": "shout", "sender": "l@uav-a", "receivers": ["echo@uav-b"]},
            _m("l@uav-a", "echo@uav-c", inform, {"i": 10}),  # for another platform
            _m("l@uav-a", "echo@uav-b", req, {"i": 11}),
            _m("l@uav-a", "echo@uav-b", req, {"i": 12}),  # over the request limit
            _m("l@uav-b", "echo@uav-b", inform, {"i": 13}),  # claims the receiver's platform
        ]
        items += [_m("l@uav-a", "echo@uav-b", inform, {"i": i}) for i in range(14, 24)]
        other = None
        if runs:
            ib.rate_limit = RateLimit(rate=1e-3, burst=6.0, total_rate=1e-3, total_burst=40.0)
            other = await serve(pb, "echo2")
            items = [
                _m("l@uav-a", "echo@uav-b", inform, {"i": 1}),
                _m("m@uav-a", "echo2@uav-b", inform, {"i": 2}),
                _m("l@uav-a", "echo@uav-b", inform, {"i": 3}),
                _m("l@uav-a", "echo@uav-b", req, {"i": 4}),
                _m("victim@uav-c", "echo@uav-b", inform, {"i": 5}),  # forged, mid-run
                _m("l@uav-a", "echo@uav-b", inform, {"i": 6}),
                _m("l@uav-a", "echo2@uav-b", req, {"i": 7}),
                _m("l@uav-a", "private@uav-b", req, {"i": 8}),  # no service, mid-run
                _m("l@uav-a", "echo2@uav-b", req, {"i": 9}),
                _m("m@uav-a", "echo@uav-b", inform, {"i": 10}),
                _m("m@uav-a", "echo@uav-b", inform, {"i": 11}, reply_to=["m@uav-a"]),
                _m("m@uav-a", "ghost@uav-b", inform, {"i": 12}),  # no such agent, mid-run
                _m("m@uav-a", "echo@uav-b", inform, {"i": 13}),
                _m("m@uav-a", "echo@uav-c", inform, {"i": 14}),  # another platform, mid-run
                _m("m@uav-a", "echo2@uav-b", inform, {"i": 15}),
                _m("l@uav-b", "echo2@uav-b", inform, {"i": 16}),  # claims uav-b, mid-run
                _m("l@uav-a", "echo2@uav-b", inform, {"i": 17}),
                _m("l@uav-a", "echo@uav-b", req, {"i": 18}),
                _m("l@uav-a", "echo@uav-b", req, {"i": 19}),
                _m("l@uav-a", "echo2@uav-b", req, {"i": 20}),  # over the request limit
                _m("m@uav-a", "echo2@uav-b", inform, {"i": 21}),
            ]
        bodies = [orjson.dumps(i) if isinstance(i, dict) else i.to_json() for i in items]
        key = wire_key(FED, "acl", "uav-b")
        raw = await fed.raw()
        seal = ia(pa).sessions.seal
        before = len(ib.audit.last(10_000))
        if batched:
            await raw.publish(key, seal("uav-b", b"[" + b",".join(bodies) + b"]"))
        else:
            for body in bodies:
                await raw.publish(key, seal("uav-b", body))
        sender = pb.stats.senders["uav-a"]
        await until(
            lambda: sender.accepted + sender.limited >= len(items) - 1, "every message decided"
        )
        await asyncio.sleep(0.2)  # the refusals and not-understoods go out
        records = [
            {k: v for k, v in r.items() if k != "ts"} for r in ib.audit.last(10_000)[before:]
        ]
        stats = pb.stats
        return {
            "records": records,
            "informs": [m.content for m in echo.informs],
            "informs2": None if other is None else [m.content for m in other.informs],
            "calls2": None if other is None else [m.content for m in other.calls],
            "calls": [m.content for m in echo.calls],
            "accepted": sender.accepted,
            "limited": sender.limited,
            "refused": sender.refused,
            "counts": dict(ib.audit.counts),
            "platform": (
                stats.received_remote,
                stats.local,
                stats.forged,
                stats.unknown_receiver,
                stats.rate_limited,
            ),
        }


def _m(sender: str, receiver: str, performative: P, content: Any, **fields: Any) -> ACLMessage:
    return ACLMessage.build(
        performative=performative,
        sender=sender,
        receivers=[receiver],
        content=content,
        ontology="demo",
        protocol="fipa-request",
        conversation_id=f"c-{content}",
        reply_with=f"r-{content}",
        **fields,
    )


async def test_a_hostile_batch_is_decided_as_its_messages_one_by_one() -> None:
    """Limits, sender binding, reply_to, access, unknown agents, audit: batch == one by one."""
    alone = await _decisions(batched=False)
    together = await _decisions(batched=True)
    assert together == alone
    assert alone["limited"] >= 2  # both limits reached


async def test_interleaved_runs_of_a_hostile_batch_are_decided_as_one_by_one() -> None:
    """Two receivers, two senders, a bad one mid-run: batch == one by one, order kept."""
    alone = await _decisions(batched=False, runs=True)
    together = await _decisions(batched=True, runs=True)
    assert together == alone
    assert alone["informs"] == [{"i": 1}, {"i": 3}, {"i": 6}, {"i": 10}, {"i": 11}, {"i": 13}]
    assert alone["informs2"] == [{"i": 2}, {"i": 15}, {"i": 17}, {"i": 21}]
    assert alone["limited"] == 1


# -- a resend waiting for room: sealed when it leaves, not when it begins to wait -----------

_SKEW = 0.3  # the receiver's allowed age of an envelope, scaled down from 30 s
_FROZEN = 0.8  # how long a put to a frozen receiver holds the worker


class _Pooled(MemoryTransport):
    """A memory transport whose blocking puts share one worker, as zenoh's share a few threads.

    A put to a frozen receiver holds it (zenoh's BLOCK waits for room in that link's
    queue); the others wait for it, as a task waits in zenoh's executor queue.
    """

    def __init__(self, hub: MemoryHub, workers: int = 1) -> None:
        super().__init__(hub)
        self.pool = asyncio.Semaphore(workers)
        self.drop_streams = False
        self.frozen_puts = 0  # puts to a frozen receiver holding a worker now

    async def publish(self, key: str, payload: bytes, *, attachment: bytes | None = None) -> None:
        """Lose stream batches while the link is down (the gap a resend fills)."""
        if self.drop_streams and "/stream/" in key:
            return
        await super().publish(key, payload, attachment=attachment)

    async def publish_blocking(self, key: str, payload: Any) -> None:
        """One at a time; a frozen receiver's put holds the worker for a while."""
        async with self.pool:
            if callable(payload):
                payload = await payload()
            if "/frozen/" in key or "/stream/uav-f/" in key:
                self.frozen_puts += 1
                try:
                    await asyncio.sleep(_FROZEN)
                finally:
                    self.frozen_puts -= 1
                return
            await super().publish(key, payload)


_sealed: dict[bytes, float] = {}


class _Stamped(PlainSessions):
    """Plain envelopes that expire, as a real session's do past the allowed skew."""

    def seal_bytes(self, peer: str, body: bytes) -> bytes:
        """Seal, remembering when."""
        envelope = super().seal_bytes(peer, body)
        _sealed[envelope] = time.monotonic()
        return envelope

    def open_bytes(self, envelope: bytes) -> tuple[str, bytes]:
        """Open, refusing an envelope sealed longer ago than the skew."""
        frm, body = super().open_bytes(envelope)
        if time.monotonic() - _sealed.get(envelope, time.monotonic()) > _SKEW:
            raise Expired("sealed too long ago", frm)
        return frm, body


async def test_a_resend_waiting_behind_a_frozen_receivers_put_is_not_lost() -> None:
    """A resend sealed, then kept waiting for the worker, would arrive expired: lost for good."""
    from test_proxies import LOCAL, SEM, Net, agreed
    from test_proxies import until as until_p

    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        ta = _Pooled(net.hub)
        _, a = await net.platform("uav-a", transport=ta)
        await net.platform("uav-b")
        src = a.add_source(LOCAL)
        exp = await net.exporter("uav-a", sessions=_Stamped("uav-a"), max_batch_bytes=1024)
        imp = await net.importer("uav-b", sessions=_Stamped("uav-b"), translate=agreed(SEM))
        export = exp.start_exporting(LOCAL, SEM, "uav-b", history=10)
        for _ in range(3):
            src.push(1)
            await asyncio.sleep(0.02)
        ta.drop_streams = True
        for _ in range(5):
            src.push(2)
            await asyncio.sleep(0.02)
        ta.drop_streams = False
        # the attacker: a frozen receiver's resend holds the worker when ours is asked
        frozen = asyncio.ensure_future(ta.publish_blocking("dyknow/x/frozen/uav-f", b"x"))
        await asyncio.sleep(0)
        src.push(3)  # the gap's end arrives: the 5 lost are asked back at once
        rec = await until_p(lambda: imp.get("uav-a", SEM), "the import")
        await until_p(lambda: export.recovered == 5, "the history resent")
        await frozen
        await asyncio.sleep(0.1)
        assert rec.recovered == 5, "a resend arrived expired: its samples are lost"


# -- one platform, one process: the duplicate seen though its link comes up a little late ----


async def _delaying_proxy(port: int, to: int, delay: float) -> asyncio.Server:
    """A TCP forwarder on ``port`` to ``to`` that connects onward ``delay`` s late."""

    async def pipe(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        with contextlib.suppress(Exception):
            while data := await r.read(65536):
                w.write(data)
                await w.drain()
        w.close()

    async def serve(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        await asyncio.sleep(delay)
        r2, w2 = await asyncio.open_connection("127.0.0.1", to)
        await asyncio.gather(pipe(r, w2), pipe(r2, w))

    return await asyncio.start_server(serve, "127.0.0.1", port)


async def test_a_second_node_of_a_name_is_refused_though_its_link_to_the_first_is_late() -> None:
    """A third platform answering first must not hide the running one still being connected."""
    from types import SimpleNamespace

    from agents.transports import ZenohConfig, ZenohTransport, free_tcp_port
    from federation._local import PlatformAliveError, refuse_duplicate

    fed = "demo"
    pa, pc, pb, proxy = (free_tcp_port() for _ in range(4))
    async with contextlib.AsyncExitStack() as stack:
        a = await stack.enter_async_context(ZenohTransport(ZenohConfig.loopback(pa)))
        c = await stack.enter_async_context(ZenohTransport(ZenohConfig.loopback(pc)))
        await a.declare_token(wire_key(fed, "alive", "x"))
        await c.declare_token(wire_key(fed, "alive", "c"))
        server = await _delaying_proxy(proxy, pa, 0.4)
        stack.push_async_callback(server.wait_closed)
        stack.callback(server.close)
        b = await stack.enter_async_context(
            ZenohTransport(ZenohConfig.loopback(pb, connect=[pc, proxy]))
        )
        with pytest.raises(PlatformAliveError):
            # no key to read: no local channel to look at, only the network
            config = SimpleNamespace(federation=fed, name="x", key=Path("no-such.key"))
            # the answer's bound: 5 s, not the default 1 s, whose 0.6 s beyond the proxy's
            # delay a loaded machine used up once before the late link was up
            await refuse_duplicate(b, config, wait=5.0)  # type: ignore[arg-type]


# -- the Gateway: reserved labels are not even named to another platform --------------------


@pytest.mark.parametrize(
    "content",
    [
        {"action": "query", "label": "nope"},  # the quick query
        {"action": "query", "label": "nope", "kind": "at", "t": 1.0},  # the models' path
        {"action": "create-stream", "label": "nope", "output": "out"},
    ],
)
async def test_an_unknown_label_refusal_names_no_reserved_label_to_another_platform(
    content: dict[str, Any],
) -> None:
    from test_gateway import world

    from agents import Refused

    async with world(visibility="protected") as w:
        w.dk.add_source("import/uav-c/secret")
        with pytest.raises(Refused) as refused:
            await w.ask(content)
        reason = str(refused.value)
        assert "unknown label 'nope'" in reason
        assert "car5-state" in reason  # what it may see is still listed
        assert "import/" not in reason


async def test_an_unknown_label_subscription_names_no_reserved_label_to_another_platform() -> None:
    from test_gateway import GW, world

    from agents import Refused, subscribe

    async with world(visibility="protected") as w:
        w.dk.add_source("import/uav-c/secret")
        with pytest.raises(Refused) as refused:
            await subscribe(w.asker, GW, {"label": "nope"}, ontology="dyknow", timeout=5)
        assert "import/" not in str(refused.value)


async def test_a_frozen_receiver_holds_one_worker_whatever_its_number_of_streams() -> None:
    """Its resends take one worker at a time: another receiver's resend (and stream) goes on."""
    from test_proxies import Net, agreed
    from test_proxies import until as until_p

    async with contextlib.AsyncExitStack() as stack:
        net = Net(stack)
        ta = _Pooled(net.hub, workers=2)
        _, a = await net.platform("uav-a", transport=ta)
        await net.platform("uav-f")
        await net.platform("uav-b")
        sources = {s: a.add_source(f"car/{s}") for s in ("f1", "f2", "b")}
        exp = await net.exporter("uav-a", max_batch_bytes=1024)
        await net.importer("uav-f", translate=agreed("f1", "f2"))
        await net.importer("uav-b", translate=agreed("b"))
        exports = {
            s: exp.start_exporting(f"car/{s}", s, "uav-b" if s == "b" else "uav-f", history=10)
            for s in sources
        }

        async def push(names: str, value: int) -> None:
            for name in names.split():
                sources[name].push(value)
            await asyncio.sleep(0.02)

        for _ in range(3):
            await push("f1 f2 b", 1)
        ta.drop_streams = True
        for _ in range(5):
            await push("f1 f2 b", 2)
        ta.drop_streams = False
        # the frozen receiver's two streams ask their resends first, and hold workers
        await push("f1 f2", 3)
        await until_p(lambda: ta.frozen_puts >= 1, "the frozen receiver's resends")
        await asyncio.sleep(0.05)  # both of its streams had their turn to take a worker
        began = time.monotonic()
        await push("b", 3)
        await until_p(lambda: exports["b"].recovered == 5, "the other receiver's resend")
        took = time.monotonic() - began
        assert took < _FROZEN / 2, f"another receiver's resend waited {took:.2f} s"
