"""`dyknow demo traffic`: the launcher, the operator station and the final report.

The launcher generates the federation's keys and configs into a run directory, starts
one OS process per UAV (spawned), and runs the operator platform itself, with its web
console. The operator delegates "monitor the area" to the leader (the first UAV), which
asks everyone's capabilities with a global request and gives each area to the cheapest
bidder by Contract-Net. While the simulated traffic runs, a progress line per second says
what each UAV sees; at the end the violations the UAVs recognized are compared with the
simulator's ground truth, with the figures of the federation's exchanges.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import multiprocessing
import secrets
import string
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

from agents import Agent, request
from agents.keys import gen_keys, trust_keys
from agents.transports import free_tcp_port
from dyknow_core import NS_PER_S, DyKnowInstance

from .._platform import FederationPlatform, PlatformConfig
from ._uav import ONTOLOGY, SPEEDING, SimClock, UavSettings, run_uav
from ._vocabulary import console_config, foxglove_config, local_mapping, vocabulary
from ._world import Violation, World

__all__ = ["DemoOptions", "DemoReport", "DemoStarted", "run_traffic_demo", "uav_names"]

FEDERATION = "traffic"
OPERATOR = "operator"
log = logging.getLogger(__name__)

START_TIMEOUT = 60.0  # s: spawned interpreters import zenoh and pydantic on 2 cores
MATCH_TIME = 3.0  # s: a recognized event matches the ground truth within this


def uav_names(n: int) -> list[str]:
    """``uav-a``, ``uav-b``, …: the UAV platforms' names."""
    if not 1 <= n <= len(string.ascii_lowercase):
        raise ValueError(f"uavs must be between 1 and 26, got {n}")
    return [f"uav-{c}" for c in string.ascii_lowercase[:n]]


@dataclass(frozen=True, slots=True)
class DemoOptions:
    """How to run the demo (the CLI's options)."""

    uavs: int = 3
    duration: float = 60.0
    seed: int = 1
    speed: float = 2.0
    console: bool = True
    host: str = "127.0.0.1"
    port: int = 8080
    run_dir: str | None = None
    hold: float = 0.0  # s to keep running (console open) after the report
    console_token: str | None = None  # None: a random one (the URL printed carries it)
    allow_hosts: tuple[str, ...] = ()  # host names the console may be reached by
    foxglove_port: int | None = None  # the operator serves Foxglove there too (0: any port)


@dataclass(frozen=True, slots=True)
class DemoStarted:
    """Handed to ``run_traffic_demo(started=…)`` once every UAV joined (tests, embedding).

    ``console_url`` is the console's URL with its token (``…/?token=…``).
    """

    console_url: str | None
    pids: dict[str, int]


@dataclass(slots=True)
class DemoReport:
    """What happened: ground truth vs recognized, and the federation's figures."""

    ground_truth: list[dict[str, Any]]
    found: list[dict[str, Any]]
    matched: list[tuple[dict[str, Any], dict[str, Any] | None]]
    false_positives: list[dict[str, Any]]
    uavs: dict[str, dict[str, Any]]
    delegation: dict[str, Any]
    figures: dict[str, Any] = field(default_factory=dict)
    console_url: str | None = None

    @property
    def handover_detected(self) -> bool:
        """The border-crossing reckless overtake was recognized, from fused states."""
        return any(
            gt["kind"] == "reckless-overtake"
            and gt["start_area"] != gt["end_area"]
            and f is not None
            and f.get("fused")
            for gt, f in self.matched
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (``dyknow demo traffic --json``)."""
        return {
            "ground-truth": self.ground_truth,
            "found": self.found,
            "matched": [{"truth": gt, "found": f} for gt, f in self.matched],
            "false-positives": self.false_positives,
            "handover-detected": self.handover_detected,
            "uavs": self.uavs,
            "delegation": self.delegation,
            "figures": self.figures,
        }


# -- files ----------------------------------------------------------------------------------


def _federation_files(
    run_dir: Path, names: list[str], federation: str = FEDERATION
) -> dict[str, dict[str, Any]]:
    """Keys, trust file and one config dict per platform (zenoh peers on loopback)."""
    keys = run_dir / "keys"
    keys.mkdir(parents=True, exist_ok=True)
    pubs = []
    for name in [*names, OPERATOR]:
        _, _, pub = gen_keys(name, keys, force=True)
        pubs.append(pub)
    trust = keys / "trust.json"
    trust.unlink(missing_ok=True)
    trust_keys(trust, pubs, federation=federation)
    ports = {name: free_tcp_port() for name in [*names, OPERATOR]}
    seed = f"tcp/127.0.0.1:{ports[OPERATOR]}"
    configs = {}
    for name in [*names, OPERATOR]:
        configs[name] = {
            "name": name,
            "federation": federation,
            "key": str(keys / f"{name}.key"),
            "trust": str(trust),
            "vocabulary": vocabulary(federation),
            "mapping": local_mapping(federation),
            "transport": {
                "kind": "zenoh",
                "mode": "peer",
                "listen": [f"tcp/127.0.0.1:{ports[name]}"],
                "connect": [] if name == OPERATOR else [seed],
            },
        }
    configs[OPERATOR]["console"] = console_config()
    configs[OPERATOR]["foxglove"] = foxglove_config()
    return configs


# -- matching -------------------------------------------------------------------------------


def _truth(v: Violation) -> dict[str, Any]:
    return {
        "kind": v.kind,
        "car": v.car,
        "other": v.other,
        "start": round(v.start, 2),
        "end": round(v.end, 2),
        "start_area": v.start_area,
        "end_area": v.end_area,
        "x": round(v.x, 1),
        "y": round(v.y, 1),
    }


def match_violations(
    truth: list[dict[str, Any]], found: list[dict[str, Any]]
) -> tuple[list[tuple[dict[str, Any], dict[str, Any] | None]], list[dict[str, Any]]]:
    """Pair each true event with a recognized one of its kind ending within MATCH_TIME s.

    Several UAVs may recognize the same event (a pair seen from two areas): any of them
    counts; a recognized event matching no true one is a false positive.
    """
    used: set[int] = set()
    pairs: list[tuple[dict[str, Any], dict[str, Any] | None]] = []
    for gt in truth:
        candidates = [
            (abs(f["end"] - gt["end"]), i)
            for i, f in enumerate(found)
            if f["kind"] == gt["kind"] and abs(f["end"] - gt["end"]) <= MATCH_TIME
        ]
        # one recognition counts for one true event
        fresh = [c for c in candidates if c[1] not in used]
        if not fresh:
            pairs.append((gt, None))
            continue
        # prefer the fused recognition of a border crossing: that is what the demo shows
        best = min(fresh, key=lambda c: (not found[c[1]].get("fused"), c[0]))[1]
        pairs.append((gt, found[best]))
        used.add(best)
    # the others near a true event of their kind are the same event seen from another
    # area: duplicates, not false positives
    extra = [
        f
        for i, f in enumerate(found)
        if i not in used
        and not any(
            f["kind"] == gt["kind"] and abs(f["end"] - gt["end"]) <= MATCH_TIME for gt in truth
        )
    ]
    return pairs, extra


# -- children --------------------------------------------------------------------------------


@contextlib.contextmanager
def _children(settings: list[UavSettings]) -> Iterator[dict[str, BaseProcess]]:
    """Spawned UAV processes, each stopped (TERM, then KILL) on the way out."""
    ctx = multiprocessing.get_context("spawn")
    procs: dict[str, BaseProcess] = {}
    try:
        for s in settings:
            p: BaseProcess = ctx.Process(target=run_uav, args=(s,), name=s.name, daemon=True)
            p.start()
            procs[s.name] = p
        yield procs
    finally:
        for p in procs.values():
            if p.is_alive():
                p.terminate()
        deadline = time.monotonic() + 5.0
        for p in procs.values():
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()
                p.join(2.0)


def _check_alive(procs: dict[str, BaseProcess]) -> None:
    dead = [f"{n} (exit code {p.exitcode})" for n, p in procs.items() if not p.is_alive()]
    if dead:
        raise RuntimeError(f"UAV process ended before joining: {', '.join(dead)}")


# -- the run ------------------------------------------------------------------------------------


Say = Callable[[str], None]


async def run_traffic_demo(
    options: DemoOptions,
    say: Say = print,
    *,
    started: asyncio.Future[DemoStarted] | None = None,
) -> DemoReport:
    """Run the whole demo; the report (also printed through ``say`` as it goes).

    ``started``, when given, gets the console's URL and the UAV processes once all joined.
    """
    if options.duration <= 0:
        raise ValueError(f"duration must be positive, got {options.duration}")
    if options.speed <= 0:
        raise ValueError(f"speed must be positive, got {options.speed}")
    names = uav_names(options.uavs)
    world = World.generate(options.seed, options.uavs, options.duration)
    with contextlib.ExitStack() as files:
        if options.run_dir is None:
            run_dir = Path(files.enter_context(tempfile.TemporaryDirectory(prefix="dyknow-demo-")))
        else:
            run_dir = Path(options.run_dir)
            run_dir.mkdir(parents=True, exist_ok=True)
        # a name of its own per run: a process of an earlier run still going (or reaching
        # a port reused since) shares no key expression with this one
        configs = _federation_files(run_dir, names, f"{FEDERATION}-{secrets.token_hex(3)}")
        t0 = time.time_ns()
        settings = [
            UavSettings(
                config=configs[name],
                index=i,
                n_uavs=options.uavs,
                seed=options.seed,
                duration=options.duration,
                speed=options.speed,
                t0_wall_ns=t0,
            )
            for i, name in enumerate(names)
        ]
        say(
            f"traffic demo: {options.uavs} UAVs, {options.duration:g} s of traffic at "
            f"{options.speed:g}x, seed {options.seed}; "
            f"{len(world.ground_truth())} scripted events"
        )
        with _children(settings) as procs:
            for name, proc in procs.items():
                say(f"  started {name} (pid {proc.pid})")
            return await _operate(options, world, configs[OPERATOR], names, procs, t0, say, started)


class _Operator(Agent):
    """The operator's own agent: delegates the monitoring, asks for status and reports."""

    def __init__(self) -> None:
        super().__init__("operator")


async def _operate(
    options: DemoOptions,
    world: World,
    config: dict[str, Any],
    names: list[str],
    procs: dict[str, BaseProcess],
    t0: int,
    say: Say,
    started: asyncio.Future[DemoStarted] | None,
) -> DemoReport:
    clock = SimClock(t0, options.speed)
    instance = DyKnowInstance(OPERATOR, clock=clock)
    cfg = PlatformConfig.from_dict(config, source="operator")
    async with instance, FederationPlatform(cfg, instance=instance, source="operator") as platform:
        console = None
        async with contextlib.AsyncExitStack() as stack:
            if options.console:
                from ..console import OperatorConsole

                def make(port: int) -> OperatorConsole:
                    return OperatorConsole(
                        platform,
                        world_map=world.to_dict(),
                        host=options.host,
                        port=port,
                        token=options.console_token,
                        allow_hosts=options.allow_hosts,
                    )

                try:
                    console = await stack.enter_async_context(make(options.port))
                except OSError as exc:
                    if options.port == 0 or exc.errno != errno.EADDRINUSE:
                        raise
                    # another demo (or anything) has the port: any free one will do
                    say(f"port {options.port} is taken ({exc.strerror}); using a free one")
                    console = await stack.enter_async_context(make(0))
                say(f"operator console: {console.login_url}")
            if options.foxglove_port is not None:
                from .._foxglove import FoxgloveBridge

                # beside the console, which asks for the same streams, it only serves them
                bridge = FoxgloveBridge(
                    platform,
                    host=options.host,
                    port=options.foxglove_port,
                    ask=console is None,
                    # the operator's one token: the console's (random unless given)
                    token=options.console_token if console is None else console.token,
                    allow_hosts=options.allow_hosts,
                )
                await stack.enter_async_context(bridge)
                say(f"operator foxglove: {bridge.login_url}")
            agent = await platform.agents.add(_Operator())
            await _wait_members(platform, names, procs, say)
            if started is not None and not started.done():
                url = console.login_url if console is not None else None
                started.set_result(
                    DemoStarted(url, {n: p.pid for n, p in procs.items() if p.pid is not None})
                )
            leader = names[0]
            say(f"operator → {leader}: monitor the area (global request + Contract-Net)")
            delegation: Any = await request(
                agent,
                f"traffic@{leader}",
                {"action": "monitor", "uavs": names},
                ontology=ONTOLOGY,
                timeout=45.0,
            )
            assert isinstance(delegation, dict)
            for area, who in sorted(delegation["assignments"].items()):
                say(f"  area {area} → {who}")
            start = float(delegation["start"])
            await _progress(agent, names, procs, clock, start, options.duration, say)
            reports = {}
            for name in names:
                if procs[name].is_alive():
                    try:
                        reports[name] = await _ask_report(agent, name)
                    except Exception as exc:  # the report then says it did not answer
                        log.warning("the report of %s could not be had: %s", name, exc)
            report = _report(world, reports, delegation, options)
            report.console_url = console.login_url if console is not None else None
            _print_report(report, say)
            if options.hold > 0:
                say(f"holding for {options.hold:g} s (console: {report.console_url})")
                await asyncio.sleep(options.hold)
            return report


async def _ask_report(agent: Agent, name: str) -> Any:
    """A UAV's final report: asked twice with a generous bound (a loaded host is slow)."""
    for attempt in (1, 2):
        try:
            return await request(
                agent, f"traffic@{name}", {"action": "report"}, ontology=ONTOLOGY, timeout=15.0
            )
        except Exception:
            if attempt == 2:
                raise
    raise AssertionError("unreachable")


async def _wait_members(
    platform: FederationPlatform, names: list[str], procs: dict[str, BaseProcess], say: Say
) -> None:
    start = time.monotonic()
    shown: set[str] = set()
    while True:
        _check_alive(procs)
        members = set(platform.members)
        for name in sorted(members - shown):
            say(f"  {name} joined ({time.monotonic() - start:.1f} s)")
        shown |= members
        if set(names) <= members:
            return
        if time.monotonic() - start > START_TIMEOUT:
            missing = ", ".join(sorted(set(names) - members))
            raise TimeoutError(f"UAVs did not join within {START_TIMEOUT:g} s: {missing}")
        await asyncio.sleep(0.1)


async def _status(agent: Agent, name: str) -> Any:
    """``name``'s status, or the error that came instead (one silent UAV is not fatal)."""
    try:
        return await request(
            agent, f"traffic@{name}", {"action": "status"}, ontology=ONTOLOGY, timeout=2.0
        )
    except Exception as exc:
        return exc


async def _progress(
    agent: Agent,
    names: list[str],
    procs: dict[str, BaseProcess],
    clock: SimClock,
    start: float,
    duration: float,
    say: Say,
) -> None:
    gone: set[str] = set()
    while True:
        for n in names:
            if n not in gone and not procs[n].is_alive():
                # the others go on: the federation is told the platform is gone
                gone.add(n)
                say(f"  {n} ended (exit code {procs[n].exitcode}); the others go on")
        alive = [n for n in names if n not in gone]
        if not alive:
            raise RuntimeError("every UAV process ended")
        now = clock.now() / NS_PER_S - start
        if now > duration:
            return
        async with asyncio.TaskGroup() as tg:
            asking = [tg.create_task(_status(agent, n), name=f"status[{n}]") for n in alive]
        statuses = [t.result() for t in asking]
        parts = []
        for n, s in zip(alive, statuses, strict=True):
            if isinstance(s, BaseException) or not isinstance(s, dict):
                parts.append(f"{n}: ?")
                continue
            extra = ""
            if s.get("handovers"):
                extra += f" handovers {s['handovers']}"
            if s.get("anchored"):
                extra += f" anchored {s['anchored']}"
            if s.get("speeding"):
                extra += f" speeding {s['speeding']}"
            parts.append(f"{n}: {s['cars']} cars, {s['violations']} events{extra}")
        say(f"t={max(now, 0.0):5.1f}/{duration:g} s  " + " | ".join(parts))
        await asyncio.sleep(1.0)


def _report(
    world: World, reports: dict[str, Any], delegation: dict[str, Any], options: DemoOptions
) -> DemoReport:
    truth = [_truth(v) for v in world.ground_truth()]
    found = sorted(
        (v for r in reports.values() for v in r.get("violations", [])), key=lambda v: v["end"]
    )
    matched, false_pos = match_violations(truth, found)
    handovers = [h for r in reports.values() for h in r.get("handovers", {}).values()]
    anchored = [a for r in reports.values() for a in r.get("anchored", {}).values()]

    def ms(values: list[Any]) -> list[float]:
        return sorted(round(float(v) * 1000, 1) for v in values if v is not None)

    figures = {
        "acl-messages-sent": sum(r["acl"]["sent"] for r in reports.values()),
        "streams-exported": sum(r["exports"] for r in reports.values()),
        "streams-imported": sum(r["imports"] for r in reports.values()),
        "handover-agreed-ms": ms([h.get("agreed-after") for h in handovers]),
        "handover-first-import-ms": ms([h.get("first-import-after") for h in handovers]),
        "anchored-after-ms": ms([a.get("matched-after") for a in anchored]),
        "import-delay-p99-ms": sorted(
            round(p99 / options.speed * 1000, 1)
            for r in reports.values()
            for _, p99 in r.get("import-delay", [])
            if p99 is not None
        ),
        "missing-reports": sorted(set(uav_names(options.uavs)) - set(reports)),
        "speeding": [
            {"platform": name, **x} for name, r in reports.items() for x in r.get("speeding", [])
        ],
    }
    # each recognition and each car flagged for speeding is one sample of the UAVs'
    # violation stream: what the operator console lists, one row each
    figures["violations-reported"] = len(found) + sum(len(x["cars"]) for x in figures["speeding"])
    return DemoReport(truth, found, matched, false_pos, reports, delegation, figures)


def _print_report(report: DemoReport, say: Say) -> None:
    say("")
    say("== report ==")
    hits = sum(1 for _, f in report.matched if f is not None)
    say(
        f"events recognized: {hits} of {len(report.matched)} scripted; "
        f"{len(report.false_positives)} false positive(s)"
    )
    for gt, f in report.matched:
        where = f"area {gt['start_area']}" + (
            f" → {gt['end_area']}" if gt["end_area"] != gt["start_area"] else ""
        )
        line = f"  {gt['kind']:<18} t={gt['start']:6.1f}–{gt['end']:6.1f}  {where:<12}"
        if f is None:
            say(line + "  MISSED")
        else:
            how = " from fused states (never saw its end)" if f.get("fused") else ""
            say(line + f"  found by {f['platform']} at t={f['end']:.1f}{how}")
    for f in report.false_positives:
        say(f"  false positive: {f['kind']} by {f['platform']} at t={f['end']:.1f}")
    fig = report.figures
    for x in fig["speeding"]:
        say(
            f"  speeding (monitor '{SPEEDING}'): {', '.join(x['cars'])} "
            f"by {x['platform']} at t={x['t']:.1f}"
        )
    flagged = sum(len(x["cars"]) for x in fig["speeding"])
    say(
        f"violations reported: {fig['violations-reported']} ({flagged} speeding), "
        "as the operator console lists them"
    )
    say(
        f"federation: {fig['acl-messages-sent']} ACL messages sent, "
        f"{fig['streams-exported']} streams exported, {fig['streams-imported']} imported"
    )
    if fig["handover-agreed-ms"]:
        say(
            f"handover: create-stream agreed in {fig['handover-agreed-ms']} ms, "
            f"first fused sample after {fig['handover-first-import-ms']} ms (wall)"
        )
    if fig["import-delay-p99-ms"]:
        say(f"imported streams, delay p99 (wall ms): {fig['import-delay-p99-ms']}")
