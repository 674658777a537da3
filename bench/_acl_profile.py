"""Where the time of an ACL message goes: ``python -m bench.acl --profile``.

Three views, from cleanest to most complete:

1. stages: each step a message takes, timed alone in this process on the very messages
   the benchmark sends (build, to_json, seal, open, from_json, audit, reply …), in µs;
2. the whole stack in one process over the in-memory transport (no network), with the
   Interface Agent and with the plain channel: what the agent layer costs end to end;
3. cProfile on both sides of the zenoh round trip and of the one-way flood between two
   processes (as ``bench.acl`` runs them), grouped by layer and divided per message.
   cProfile slows Python code about 1.5-2x, so the flood's groups are also scaled to
   the unprofiled CPU time per message of the loop thread, measured just before ("≈ µs").
"""

from __future__ import annotations

import cProfile
import gc
import os
import pstats
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import orjson

from agents import (
    ACLMessage,
    Agent,
    AgentPlatform,
    MemoryHub,
    Performative,
    new_id,
    run,
)
from agents._interface import AuditLog, InterfaceAgent, RateLimit
from agents._security import Handshake, KeyPair, SessionTable, TrustStore
from bench import acl
from bench._acl_node import FLOOD_ONTOLOGY, Gateway, add_gateway
from dyknow_core import DyKnowInstance

N_FLOOD = 50_000
_UNLIMITED = RateLimit(rate=1e6, burst=1e6, total_rate=1e6, total_burst=1e6)


def _per_call(fn: Callable[[], Any], n: int = 20_000) -> float:
    """µs per call of ``fn``, best of 3 runs of ``n`` (garbage collection left on, as live)."""
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(n):
            fn()
        best = min(best, time.perf_counter() - t)
    return best / n * 1e6


def _sessions() -> tuple[SessionTable, SessionTable]:
    """Two session tables (here → there) holding one session made by a real handshake."""
    ka, kb = KeyPair.generate(acl.HERE), KeyPair.generate(acl.THERE)
    trust = TrustStore(acl.FEDERATION, {acl.HERE: ka.public_key, acl.THERE: kb.public_key})
    ha, hb = Handshake(ka, trust), Handshake(kb, trust)
    reply, sb = hb.respond(ha.initiate(acl.THERE))
    sa = ha.finish(reply)
    ta, tb = SessionTable(acl.HERE, trust), SessionTable(acl.THERE, trust)
    ta.add(sa)
    tb.add(sb)
    return ta, tb


def _opening(ta: SessionTable, tb: SessionTable, body: bytes, n: int = 20_000) -> float:
    """µs per ``open`` of fresh envelopes (each counter is accepted once only)."""
    best = float("inf")
    for _ in range(3):
        envelopes = [ta.seal(acl.THERE, body) for _ in range(n)]
        t = time.perf_counter()
        for e in envelopes:
            tb.open(e)
        best = min(best, time.perf_counter() - t)
    return best / n * 1e6


def stages() -> list[tuple[str, float]]:
    """Each step of the request, the inform and a flood message, timed alone (µs)."""
    ta, tb = _sessions()
    instance = DyKnowInstance(acl.THERE)
    source = instance.add_source(acl.LABEL)
    source.push(12.5)
    gateway = Gateway("gateway", instance)

    def build_request() -> ACLMessage:
        return ACLMessage(
            performative=Performative.REQUEST,
            sender=f"asker@{acl.HERE}",
            receivers=[acl.GATEWAY],
            content=acl.QUERY,
            language="json",
            ontology="dyknow",
            protocol="fipa-request",
            conversation_id=new_id("c"),
            reply_with=new_id("r"),
            reply_by=time.time() + 5,
        )

    req = build_request()
    req_json = req.to_json()
    result = gateway.service.perform(req.content)
    inform = req.reply(Performative.INFORM, result, sender=acl.GATEWAY)
    inform_json = inform.to_json()
    flood_msg = ACLMessage(
        performative=Performative.INFORM,
        sender=f"asker@{acl.HERE}",
        receivers=[acl.SINK],
        content={"seq": 12345, "speed": 12.5, "pad": "x" * 200},
        ontology=FLOOD_ONTOLOGY,
    )
    flood_json = flood_msg.to_json()
    env = ta.seal(acl.THERE, req_json)
    obj = orjson.loads(req_json)
    audit = AuditLog()
    base = {
        "from": acl.HERE,
        "sender": req.sender,
        "receivers": req.receivers,
        "performative": req.performative.value,
        "conversation_id": req.conversation_id,
    }

    def audit_one() -> None:
        audit.record(verdict="accepted", **base, reason=None)
        if len(audit._pending) >= 250:  # the flush every 0.25 s, amortized
            audit.take()

    rows = [
        (f"request: build (ACLMessage(...), {len(req_json)} B)", _per_call(build_request)),
        ("request: to_json (model_dump + orjson)", _per_call(req.to_json)),
        ("  of which model_dump(mode='json')", _per_call(lambda: req.model_dump(mode="json"))),
        ("  of which orjson.dumps", _per_call(lambda: orjson.dumps(obj))),
        (f"request: seal ({len(env)} B envelope)", _per_call(lambda: ta.seal(acl.THERE, req_json))),
        ("request: open (parse, MAC, replay)", _opening(ta, tb, req_json)),
        (
            "request: from_json (orjson + validate)",
            _per_call(lambda: ACLMessage.from_json(req_json)),
        ),
        ("  of which orjson.loads", _per_call(lambda: orjson.loads(req_json))),
        ("  of which model_validate", _per_call(lambda: ACLMessage.model_validate(obj))),
        ("request: audit record (+ flush amortized)", _per_call(audit_one)),
        ("gateway: perform the query", _per_call(lambda: gateway.service.perform(req.content))),
        (
            "inform: build (message.reply)",
            _per_call(lambda: req.reply(Performative.INFORM, result, sender=acl.GATEWAY)),
        ),
        (f"inform: to_json ({len(inform_json)} B)", _per_call(inform.to_json)),
        # the responder seals on the session "request: open" confirmed (it has received)
        ("inform: seal", _per_call(lambda: tb.seal(acl.HERE, inform_json))),
        ("inform: from_json", _per_call(lambda: ACLMessage.from_json(inform_json))),
        (f"flood inform: to_json ({len(flood_json)} B)", _per_call(flood_msg.to_json)),
        ("flood inform: seal", _per_call(lambda: ta.seal(acl.THERE, flood_json))),
        ("flood inform: open", _opening(ta, tb, flood_json)),
        ("flood inform: from_json", _per_call(lambda: ACLMessage.from_json(flood_json))),
    ]
    return rows


async def _in_process(with_interface: bool, n: int = 3000) -> float:
    """Median µs of the request → inform round trip with both platforms in this process."""
    ka, kb = KeyPair.generate(acl.HERE), KeyPair.generate(acl.THERE)
    trust = TrustStore(acl.FEDERATION, {acl.HERE: ka.public_key, acl.THERE: kb.public_key})
    hub = MemoryHub()
    instance = DyKnowInstance(acl.THERE)
    instance.add_source(acl.LABEL).push(12.5)

    def channel(k: KeyPair) -> Any:
        # the limiter runs, but high enough for back-to-back requests in one process
        # (faster than the default 5000 requests/s of one platform)
        return InterfaceAgent(k, trust, rate_limit=_UNLIMITED) if with_interface else None

    async with (
        hub.transport() as ta,
        hub.transport() as tb,
        AgentPlatform(acl.HERE, ta, federation=acl.FEDERATION, channel=channel(ka)) as pa,
        AgentPlatform(acl.THERE, tb, federation=acl.FEDERATION, channel=channel(kb)) as pb,
    ):
        await add_gateway(pb, instance)
        asker = await pa.add(Agent("asker"))
        ms = await acl.round_trips(asker, 300, "warm-up")
        ms = await acl.round_trips(asker, n, "in-process")
    return acl.summary(ms)["median"] * 1e3


# --------------------------------------------------------------------------- cProfile

# the Interface Agent's modules: agents/_interface.py and its parts
_INTERFACE_FILES = (
    "agents/_audit.py",
    "agents/_interface.py",
    "agents/_interface_admit.py",
    "agents/_interface_common.py",
    "agents/_interface_lane.py",
    "agents/_interface_owner.py",
    "agents/_interface_presence.py",
    "agents/_interface_receive.py",
    "agents/_interface_sessions.py",
    "agents/_interface_state.py",
)

# (group, test on (file, function name)): the first that matches wins
_GROUPS: list[tuple[str, Callable[[str, str], bool]]] = [
    ("idle: waiting in epoll", lambda f, n: "poll' of 'select" in n or "select.epoll" in n),
    ("audit log", lambda f, n: f.endswith(_INTERFACE_FILES) and n in ("record", "take")),
    (
        "seal / open (MAC, envelope)",
        lambda f, n: (
            f.endswith("agents/_security.py")
            or "_hashlib.HMAC" in n
            or "binascii" in n
            or "compare_digest" in n
            or "_struct.Struct" in n
        ),
    ),
    ("JSON (orjson dumps/loads)", lambda f, n: "orjson" in n),
    (
        "runtime (platform, agent, protocol)",
        lambda f, n: f.endswith("agents/_acl.py") and n in ("platform_of", "name_of", "new_id"),
    ),
    (
        "pydantic (validate, dump, copy)",
        lambda f, n: "/pydantic" in f or "pydantic_core" in n or f.endswith("agents/_acl.py"),
    ),
    ("interface agent (receive, admit)", lambda f, n: f.endswith(_INTERFACE_FILES)),
    (
        "transport (zenoh, inbox, put)",
        lambda f, n: (
            "/agents/transports/" in f or "zenoh" in n or "_thread.lock" in n or "threading" in f
        ),
    ),
    (
        "runtime (platform, agent, protocol)",
        lambda f, n: (
            f.endswith(("agents/_platform.py", "agents/_agent.py", "agents/_protocols.py"))
            or f.endswith("agents/_df.py")
        ),
    ),
    ("asyncio (loop, futures, tasks)", lambda f, n: "/asyncio/" in f or "_asyncio" in n),
    ("gateway + dyknow query", lambda f, n: "_gateway" in f or "/dyknow_core/" in f),
    ("benchmark code", lambda f, n: "/bench/" in f),
]


def _group(file: str, name: str) -> str:
    for group, test in _GROUPS:
        if test(file, name):
            return group
    return "other (builtins: time, dict, isinstance …)"


def _label(key: tuple[str, int, str]) -> str:
    file, line, name = key
    if file == "~":
        return name
    parts = Path(file).parts
    short = "/".join(parts[-2:]) if len(parts) > 1 else file
    return f"{short}:{line}({name})"


def grouped(path_or_prof: Any, per: int, scale_to_us: float | None, top: int = 12) -> str:
    """A profile as µs per message by layer, then its costliest functions (own time)."""
    st = pstats.Stats(path_or_prof)
    raw: dict[tuple[str, int, str], tuple[Any, ...]] = st.stats  # type: ignore[attr-defined]
    groups: dict[str, float] = {}
    funcs: list[tuple[float, int, tuple[str, int, str]]] = []
    for key, (_cc, nc, tt, _ct, _callers) in raw.items():
        g = _group(key[0], key[2])
        groups[g] = groups.get(g, 0.0) + tt
        funcs.append((tt, nc, key))
    idle = groups.pop("idle: waiting in epoll", 0.0)
    busy = sum(groups.values())
    scale = (scale_to_us / (busy / per * 1e6)) if scale_to_us else None
    lines = [
        f"    busy {busy / per * 1e6:.1f} µs/msg profiled (+ {idle / per * 1e6:.1f} idle)"
        + (f"; unprofiled {scale_to_us:.1f} µs/msg" if scale_to_us else "")
    ]
    for g, tt in sorted(groups.items(), key=lambda kv: -kv[1]):
        us = tt / per * 1e6
        share = tt / busy * 100 if busy else 0.0
        est = f"  ≈ {us * scale:5.1f} µs" if scale else ""
        lines.append(f"    {g:<40} {us:6.1f} µs/msg profiled {share:4.0f}%{est}")
    lines.append("    costliest functions (own time, µs/msg profiled, calls/msg):")
    for tt, nc, key in sorted(funcs, reverse=True)[: top + 1]:
        if _group(key[0], key[2]).startswith("idle"):
            continue
        lines.append(f"      {tt / per * 1e6:6.2f}  {nc / per:5.2f}  {_label(key)}")
    return "\n".join(lines)


async def _profiled(keydir: Path, out: Path) -> None:
    async with acl.asker_side(keydir) as side:
        _, _, asker, presence, child_config = side
        with acl.node("zenoh", child_config, keydir).start() as child:
            await acl.wait_alive(presence, child, True)
            await acl.first_reply(asker, child)
            print(f"  node pid {child.pid} (py-spy can attach to it now)", flush=True)
            await acl.round_trips(asker, acl.WARMUP, "warm-up")
            n = acl.N_RTT
            plain = acl.summary(await acl.round_trips(asker, n, "unprofiled"))
            await acl.control(asker, "profile-start")
            prof = cProfile.Profile()
            prof.enable()
            await acl.round_trips(asker, n, "profiled")
            prof.disable()
            there = await acl.control(asker, "profile-stop", path=str(out / "rtt-node.prof"))
            prof.dump_stats(out / "rtt-here.prof")
            # the parent measures the whole round trip; the node only its half, so the
            # unprofiled figure is not split between them
            print(
                f"zenoh round trip, {n} requests: unprofiled median {plain['median'] * 1e3:.0f}"
                f" µs, p99 {plain['p99'] * 1e3:.0f} µs"
            )
            print("  this side (asker: build request, seal, publish; open, parse inform):")
            print(grouped(str(out / "rtt-here.prof"), n, None))
            print("  the node (open, parse, admit, audit, gateway, reply, seal, publish):")
            print(grouped(there["path"], n, None))

            gc.collect()
            plain_flood = await acl.flood(asker, N_FLOOD)
            await acl.control(asker, "profile-start")
            prof = cProfile.Profile()
            prof.enable()
            f = await acl.flood(asker, N_FLOOD)
            prof.disable()
            there = await acl.control(asker, "profile-stop", path=str(out / "flood-node.prof"))
            prof.dump_stats(out / "flood-here.prof")
            pf = plain_flood
            print(
                f"one-way flood, {N_FLOOD:,} informs, unprofiled: end to end {pf['rate']:.0f}/s;"
                f" sender {pf['sent_rate']:.0f}/s, {pf['sender_loop_us']:.1f} µs CPU/msg on its"
                f" loop thread ({pf['sender_cpu_us']:.1f} whole process); node"
                f" {pf['recv_rate']:.0f}/s, {pf['node_loop_us']:.1f} µs CPU/msg on its loop thread"
                f" ({pf['node_cpu_us']:.1f} whole process, GC {pf['gc_share'] * 100:.0f}% of the"
                f" loop's); {pf['received']:,} of {pf['sent']:,} delivered"
                f" (profiled: {f['received']:,})"
            )
            gens = ", ".join(
                f"gen{g} {r} runs {ms:.0f} ms" for g, (r, ms) in enumerate(pf["gc_by_gen"])
            )
            print(f"  the node's garbage collector over those {pf['received']:,} messages: {gens}")
            print("  sender (build, to_json, seal, put), scaled to its loop thread's CPU:")
            print(grouped(str(out / "flood-here.prof"), N_FLOOD, pf["sender_loop_us"]))
            print("  node (open, from_json, admit, audit, deliver, handler), same scaling:")
            print(grouped(there["path"], max(1, int(f["received"])), pf["node_loop_us"]))


def profile() -> None:
    """Print the per-stage costs, the in-process stack, and both sides' profiles over zenoh."""
    print("stages, each timed alone in one process (µs per message, best of 3):")
    for what, us in stages():
        print(f"  {what:<50} {us:7.2f}")
    for with_interface in (True, False):
        us = run(_in_process(with_interface))
        what = "interface agent (MAC sessions, audit)" if with_interface else "plain channel"
        print(f"whole stack in one process over the memory transport, {what}: median {us:.0f} µs")
    out = Path(os.environ.get("ACL_PROFILE_DIR") or tempfile.mkdtemp(prefix="acl-profile-"))
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="bench-acl-") as tmp:
        keydir = Path(tmp)
        acl.make_keys(keydir)
        run(_profiled(keydir, out))
    print(f"profiles in {out} (pstats files: rtt-here, rtt-node, flood-here, flood-node)")
