"""The remote node of ``bench.acl``: a whole platform in its own OS process.

Started with the ``spawn`` method (never fork once a zenoh session is open). It loads its
key pair and the trust file from disk, opens the transport, the platform with the
Interface Agent as its channel (authentication, encryption and audit on: the defaults;
the rate limit of a platform's messages raised for the flood, `FLOOD_LIMIT`) and three
agents:

- ``gateway``: answers FIPA-Request ``{"action": "query", ...}`` on a DyKnow instance
  holding a few samples of one label: the `GatewayAgent` (``federation/_gateway.py``) when
  it is importable, else a stand-in doing the same through `GatewayService`; its
  service is protected, so the Interface Agent lets other platforms of the federation
  use it;
- ``sink``: counts the one-way ``inform`` messages of the throughput test;
- ``control``: the parent's knobs, over ACL too: the sink's count, reset, cProfile on/off.

It tells the parent, through a queue, when each step of its start finished (wall clock,
so the parent can place them after the moment it spawned us), then idles until the
parent sets ``stop`` or goes away.
"""

from __future__ import annotations

import time

_T_MODULE = time.time()  # before the heavy imports: where the interpreter's start ends

import gc  # noqa: E402
import multiprocessing  # noqa: E402

from federation._cli_node import skip_pydantic_plugin_scan  # noqa: E402

# The spawned node imports as `dyknow node` does (federation._cli_node.run_node): the
# collector off while the imports build what lives as long as the node, then all of it
# frozen out of its sight; pydantic's plugin search spared when no distribution declares
# a plugin. Not in the parent, which imports this module for its names only.
_NODE = multiprocessing.parent_process() is not None
if _NODE:
    gc.disable()
    skip_pydantic_plugin_scan()

import asyncio  # noqa: E402
import cProfile  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

from agents import (  # noqa: E402
    ACLMessage,
    Agent,
    AgentPlatform,
    InterfaceAgent,
    KeyPair,
    MessageTemplate,
    Performative,
    RateLimit,
    Refuse,
    SecurityPolicy,
    ServiceDescription,
    TrustStore,
    on,
    on_request,
    run,
)
from agents.transports import (  # noqa: E402
    MqttConfig,
    MqttTransport,
    Transport,
    ZenohConfig,
    ZenohTransport,
)
from dyknow_core import DyKnowInstance  # noqa: E402
from federation import GatewayRefusal, GatewayService  # noqa: E402

try:  # the Gateway Agent proper, once it is there; else the stand-in below
    from federation import GatewayAgent
except ImportError:  # pragma: no cover - depends on the state of agents/
    GatewayAgent = None  # type: ignore[assignment,misc]

if _NODE:
    gc.freeze()
    gc.enable()
_T_IMPORTED = time.time()

LABEL = "bench/speed"
FLOOD_ONTOLOGY = "bench-flood"
CONTROL_ONTOLOGY = "bench-control"
FLOOD_LIMIT = RateLimit(total_rate=1_000_000.0, total_burst=1_000_000.0)
"""The node's rate limit: the default but for all messages of a platform, which would let
50,000 a second through (bursts of as many) and drop the rest of the flood: a policy for a
deployment, not a cost of the stack. Every message still takes its token."""


class GcClock:
    """Time spent in the garbage collector, per generation, since the last reset."""

    def __init__(self) -> None:
        self.reset()
        self._t = 0.0

    def reset(self) -> None:
        """Forget what was counted."""
        self.seconds = [0.0, 0.0, 0.0]
        self.runs = [0, 0, 0]

    def __call__(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._t = time.perf_counter()
        else:
            g = info["generation"]
            self.seconds[g] += time.perf_counter() - self._t
            self.runs[g] += 1


GC = GcClock()


class Gateway(Agent):
    """The stand-in for the Gateway Agent: FIPA-Request content performed on an instance."""

    def __init__(self, name: str, instance: DyKnowInstance) -> None:
        super().__init__(name)
        self.service = GatewayService(instance)

    @on_request("dyknow")
    async def perform(self, message: ACLMessage) -> Any:
        """Do what the request's content asks (list labels, query …); refuse what is wrong."""
        try:
            return self.service.perform(message.content)
        except GatewayRefusal as exc:
            raise Refuse(exc.reason) from None


class Sink(Agent):
    """Counts the flood's informs: how many, when the first and the last arrived, CPU used.

    Times are ``time.monotonic()``: one clock for every process of the machine, so the
    sender can measure from its first send to our last delivery.
    """

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.reset()

    def reset(self) -> None:
        """Start counting afresh."""
        self.n = 0
        self.t0 = 0.0
        self.t1 = 0.0
        self.cpu0 = time.process_time()
        self.main0 = time.thread_time()
        running = self._platform is not None
        self.dropped0 = self.inbox_dropped() if running else 0
        self.full0 = self.platform.stats.mailbox_full if running else 0
        self.limited0 = self.platform.stats.rate_limited if running else 0

    def inbox_dropped(self) -> int:
        """Messages the channel's full inbox dropped so far (a private look, for the bench)."""
        subs = getattr(self.platform.channel, "_subs", ())
        return sum(int(getattr(sub, "dropped", 0)) for sub in subs)

    def counts(self) -> dict[str, Any]:
        """What was counted since the reset (CPU seconds: the process, its event loop thread)."""
        return {
            "inbox_dropped": self.inbox_dropped() - self.dropped0,
            "mailbox_full": self.platform.stats.mailbox_full - self.full0,
            "rate_limited": self.platform.stats.rate_limited - self.limited0,
            "n": self.n,
            "t0": self.t0,
            "t1": self.t1,
            "cpu_s": time.process_time() - self.cpu0,
            "main_s": time.thread_time() - self.main0,
            "gc_s": GC.seconds,
            "gc_runs": GC.runs,
        }

    @on(MessageTemplate(Performative.INFORM, ontology=FLOOD_ONTOLOGY))
    async def count(self, message: ACLMessage) -> None:
        """One more inform delivered to this agent."""
        now = time.monotonic()
        if not self.n:
            self.t0 = now
        self.n += 1
        self.t1 = now


class Control(Agent):
    """The parent's remote control: counts, reset, profiling of this process's event loop."""

    def __init__(self, name: str, sink: Sink) -> None:
        super().__init__(name)
        self.sink = sink
        self.profiler: cProfile.Profile | None = None

    @on_request(CONTROL_ONTOLOGY)
    async def handle(self, message: ACLMessage) -> Any:
        """``{"op": "count" | "reset" | "profile-start" | "profile-stop", "path": …}``."""
        content = message.content if isinstance(message.content, dict) else {}
        op = content.get("op")
        sink = self.sink
        if op == "count":
            return sink.counts()
        if op == "reset":
            sink.reset()
            GC.reset()
            return {"n": 0}
        if op == "profile-start":
            self.profiler = cProfile.Profile()
            self.profiler.enable()
            return {"profiling": True}
        if op == "profile-stop":
            prof, self.profiler = self.profiler, None
            if prof is None:
                raise Refuse("not profiling")
            prof.disable()
            path = str(content.get("path") or f"/tmp/acl-node-{os.getpid()}.prof")
            prof.dump_stats(path)
            return {"path": path}
        raise Refuse(f"unknown op {op!r}")


async def add_gateway(host: AgentPlatform, instance: DyKnowInstance) -> str:
    """Add ``gateway@<host>`` with its protected ``dyknow`` service; says which one it is."""
    if GatewayAgent is not None:  # registers its service itself (protected by default)
        await host.add(GatewayAgent(instance, name="gateway"))
        return "GatewayAgent (federation/_gateway.py)"
    assert host.df is not None
    gateway = await host.add(Gateway("gateway", instance))
    await host.df.register(
        ServiceDescription(
            name="dyknow", type="dyknow", provider=gateway.aid, visibility="protected"
        )
    )
    return "stand-in gateway (GatewayService in bench/_acl_node.py)"


def _transport(kind: str, config: dict[str, Any]) -> Transport:
    if kind == "zenoh":
        return ZenohTransport(ZenohConfig.model_validate(config))
    if kind == "mqtt":
        return MqttTransport(MqttConfig.model_validate(config))
    raise ValueError(f"unknown transport {kind!r}")


async def _serve(
    kind: str,
    config: dict[str, Any],
    keydir: str,
    platform: str,
    federation: str,
    reports: Any,
    stop: Any,
    encrypt: bool = True,
) -> None:
    parent = os.getppid()
    marks = {"module": _T_MODULE, "imported": _T_IMPORTED}
    keys = KeyPair.load(Path(keydir) / f"{platform}.key")
    trust = TrustStore.load(Path(keydir) / "trust.json")
    instance = DyKnowInstance(platform)
    source = instance.add_source(LABEL)
    for v in (12.0, 12.5, 13.1):
        source.push(v)
    marks["keys"] = time.time()
    async with _transport(kind, config) as transport:
        marks["transport"] = time.time()
        channel = InterfaceAgent(
            keys, trust, policy=SecurityPolicy(encrypt=encrypt), rate_limit=FLOOD_LIMIT
        )
        async with AgentPlatform(
            platform, transport, federation=federation, channel=channel
        ) as host:
            marks["platform"] = time.time()
            assert host.df is not None
            responder = await add_gateway(host, instance)
            sink = await host.add(Sink("sink"))
            control = await host.add(Control("control", sink))
            await host.df.register(
                ServiceDescription(
                    name=CONTROL_ONTOLOGY,
                    type=CONTROL_ONTOLOGY,
                    provider=control.aid,
                    visibility="protected",
                )
            )
            marks["ready"] = time.time()
            reports.put(("ready", os.getpid(), {"marks": marks, "responder": responder}))
            # as a node does once started (federation's settle_gc): what start-up built
            # lives as long as the process, out of the collector's sight
            gc.collect()
            gc.freeze()
            # a multiprocessing Event cannot be awaited: poll it (and the parent's life)
            while not stop.is_set() and os.getppid() == parent:  # noqa: ASYNC110
                await asyncio.sleep(0.1)
            if control.profiler is not None:
                control.profiler.disable()


def node_main(
    kind: str,
    config: dict[str, Any],
    keydir: str,
    platform: str,
    federation: str,
    reports: Any,
    stop: Any,
    encrypt: bool = True,
) -> None:
    """The child process: serve as ``platform`` until ``stop`` is set (errors go to ``reports``).

    ``encrypt``: its sessions' policy (the default, as platforms; False: MAC only).
    """
    gc.callbacks.append(GC)
    try:
        run(_serve(kind, config, keydir, platform, federation, reports, stop, encrypt))
    except Exception:
        # the parent raises it with this traceback; exiting quietly avoids printing it twice
        reports.put(("error", os.getpid(), traceback.format_exc()))
        sys.exit(1)
    reports.put(("stopped", os.getpid(), None))
