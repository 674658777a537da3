"""One UAV of the traffic demo: its own DyKnow instance and federation platform, one process.

The local DyKnow application (never changed for the federation's sake):

* the camera (`Camera` of the simulated world) gives vision percepts, relative to the UAV;
* anchoring (`dyknow_core` classes and links): VisionObject → WorldObject (co-located with
  the UAV's own position at capture time) → OnRoadObject (on a road for 10 s; kept while
  not off-road for more than 5 s) → Car;
* a tracker publishes each world object's state (``car/<object>/state``), the cars it
  tracks (``tracker/cars``) and the qualitative relations between cars (behind, beside,
  beside-fast, in-front) and crossing events as event streams;
* chronicles recognize overtakes, reckless overtakes and turns in crossings; recognitions
  become ``violation`` samples, and so does each car the speed monitor flags (kind
  ``speeding``): the operator's console lists every violation from that one stream;
* the cars tracked now are the domain `TRACKED` (by their federation names), whose facts
  (`fact_rules`: ``(Car uav_b_car3)``, ``(Colour uav_b_car3 red)``) answer label
  searches such as ``(all ?x (Car ?x))`` with the tracked cars' ``{object}-state`` labels.

The federation part: the `TrafficMonitor` agent takes part in the leader's delegation
(global request for capabilities, Contract-Net per area). When a possible violation is
about to leave this UAV's area, it asks the neighbour for the cars' states
(``create-stream <object>-state sample-period 0.5``) and fuses them with its own; the
neighbour anchors the object through `anchor_object` (get-trajectory from the asker, then
match it among its own world objects) and exports its states as soon as it sees it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import multiprocessing
import re
import signal
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Self

from agents import (
    ACLMessage,
    Agent,
    MessageTemplate,
    Performative,
    Proposal,
    Refuse,
    ServiceDescription,
    Visibility,
    contract_net,
    on,
    on_accept_proposal,
    on_cfp,
    on_request,
    platform_of,
)
from dyknow_core import NS_PER_S, Domain, DyKnowInstance, Sample, Source
from dyknow_core.reasoning import (
    Anchoring,
    LinkType,
    ObjectClass,
    add_anchoring,
    add_chronicle,
    add_monitor,
)
from ontology import DomainRule, Rule, StreamRule

from .._cli_common import settle_gc
from .._platform import FederationPlatform, PlatformConfig
from ._traffic import (
    CHRONICLES,
    CROSSING_EVENTS,
    RELATIONS,
    SPEEDING,
    RelationChanges,
    crossing_step,
    is_fast,
    is_repeat,
)
from ._world import Camera, World

__all__ = [
    "BASE_S",
    "SERVICE_TYPE",
    "TRACKED",
    "SimClock",
    "TrafficMonitor",
    "UavSettings",
    "fact_rules",
    "run_uav",
    "tracked_domain",
]

log = logging.getLogger(__name__)

BASE_S = 1000.0
"""Instance clock seconds at the demo's launch: sim times stay positive before it."""
BASE_NS = int(BASE_S * NS_PER_S)
SERVICE_TYPE = "traffic-monitoring"
ONTOLOGY = "traffic-demo"
PERIOD = 0.2  # s (sim): camera, anchoring and tracker period
FRESH = 1.5  # s: a state older than this is no longer tracked
FUSED_FRESH = 2.5  # s: imported states come on a 0.5 s grid, later (moved on to the step)
HANDOVER_RANGE = 150.0  # m before the east border: ask the neighbour for the cars
MIN_POINTS = 4  # positions before a track has a state: two give a noisy speed
MISSES = 3  # detections missed in a row before a percept is retired
MATCH = 15.0  # m: an anchored object's predicted position vs a local world object
MEMBERS_WAIT = 10.0  # s: the leader waits at most this for the UAVs the operator saw join
CAPABILITIES_DEADLINE = 10.0  # s: for every member's capabilities (returns when all answered)
OBJECT_STATE = re.compile(r"([A-Za-z0-9_]+)-state")
TRACKED = "tracked"
"""The domain of the cars a UAV tracks now, by their federation names (``uav_b_car3``)."""


def fact_rules() -> list[Rule]:
    """The facts a UAV's label search answers from: each tracked car and its colour."""
    return [
        DomainRule(TRACKED, "Car"),
        StreamRule("car/{object}/state", "Colour", domain=TRACKED, convert=_colour),
    ]


def _colour(state: Any) -> Any:
    return state.get("colour") if isinstance(state, dict) else None


def tracked_domain(dk: DyKnowInstance) -> Domain:
    """The instance's `TRACKED` domain, made on first use (before the fact feed needs it)."""
    if TRACKED not in dk.objects.domains():
        dk.objects.add_domain(TRACKED)
    return dk.objects.domain(TRACKED)


class SimClock:
    """Simulated time shared by the demo's processes: ``speed`` x wall time since ``t0``.

    Every process computes it from the same wall-clock origin, so their instances agree
    (up to the hosts' clock skew, nil on one host).
    """

    __slots__ = ("_speed", "_t0")

    def __init__(self, t0_wall_ns: int, speed: float = 1.0) -> None:
        if speed <= 0 or not math.isfinite(speed):
            raise ValueError(f"speed must be a positive number, got {speed}")
        self._t0 = t0_wall_ns
        self._speed = speed

    def now(self) -> int:
        """Instance time, ns: ``BASE_S`` at the launch."""
        return BASE_NS + int((time.time_ns() - self._t0) * self._speed)

    async def sleep_until(self, t: int) -> None:
        """Sleep until instance time ``t``."""
        wall = self._t0 + (t - BASE_NS) / self._speed
        delay = (wall - time.time_ns()) / NS_PER_S
        # late too, it yields: a loop behind time (a busy machine) catching up step after
        # step would otherwise hold the event loop, and nothing else (requests, handovers,
        # imports) would run until it caught up
        await asyncio.sleep(max(delay, 0.0))


@dataclass(frozen=True, slots=True)
class UavSettings:
    """What the demo's launcher tells one UAV process."""

    config: dict[str, Any]  # the platform's config, as `PlatformConfig.from_dict` takes it
    index: int
    n_uavs: int
    seed: int
    duration: float
    speed: float
    t0_wall_ns: int

    @property
    def name(self) -> str:
        """The platform's name."""
        return str(self.config["name"])


# -- the tracker's small state, per object ----------------------------------------------------


@dataclass(slots=True)
class _Track:
    """Recent positions of one world object (least squares over the last second)."""

    points: deque[tuple[float, float, float]] = field(default_factory=lambda: deque(maxlen=6))
    crossing: str | None = None
    entry_road: str | None = None
    last_road: str | None = None

    def add(self, t: float, x: float, y: float) -> None:
        if self.points and self.points[-1][0] >= t:
            return
        self.points.append((t, x, y))

    def state(
        self, t: float, world: World | None = None
    ) -> tuple[float, float, float, float] | None:
        """Smoothed position at ``t`` and velocity: (x, y, vx, vy).

        The line through the points gives where the object was when last seen; from there
        to ``t`` it is moved on along its road (``world``'s, the one its heading follows),
        not sideways. A second of positions with 0.5 m noise gives the sideways speed to
        ±0.6 m/s only: carried on for the age of the newest position (a second on a busy
        machine), it puts a car beside another in that car's lane for a step, and the
        relation `in-front` (never taken back) ends an overtake seconds early. A lane
        change is seen as it happens, late by that age at most. Turning (its heading off
        every road here) or without a ``world``, it is moved on in a straight line.
        """
        pts = self.points
        n = len(pts)
        if n < MIN_POINTS:
            return None
        mt = sum(p[0] for p in pts) / n
        mx = sum(p[1] for p in pts) / n
        my = sum(p[2] for p in pts) / n
        var = sum((p[0] - mt) ** 2 for p in pts)
        if var <= 0:
            return None
        vx = sum((p[0] - mt) * (p[1] - mx) for p in pts) / var
        vy = sum((p[0] - mt) * (p[2] - my) for p in pts) / var
        seen = pts[-1][0]
        x, y = mx + vx * (seen - mt), my + vy * (seen - mt)
        road = None if world is None else _road_direction(world, x, y, vx, vy)
        ux, uy = (vx, vy) if road is None else _along(vx, vy, road)
        return x + ux * (t - seen), y + uy * (t - seen), vx, vy


_ALIGNED = math.cos(math.radians(30.0))
"""A heading within 30° of a road's follows it (a lane change's is within 7.5°)."""


def _road_direction(
    world: World, x: float, y: float, vx: float, vy: float
) -> tuple[float, float] | None:
    """The unit direction of the road a car at (x, y) heading (vx, vy) follows, or None.

    In a crossing, the one of its roads the heading follows; None off road, standing,
    or turning (the heading off every road here by more than 30°).
    """
    speed = math.hypot(vx, vy)
    if speed <= 0:
        return None
    here = world.crossing_at(x, y)
    if here is not None:
        names: tuple[str | None, ...] = next(c.roads for c in world.crossings if c.id == here)
    else:
        names = (world.road_at(x, y),)
    best, best_cos = None, _ALIGNED
    for road in world.roads:
        if road.id in names:
            u = _unit(road.b[0] - road.a[0], road.b[1] - road.a[1])
            cos = abs(u[0] * vx + u[1] * vy) / speed
            if cos >= best_cos:
                best, best_cos = u, cos
    return best


def _along(vx: float, vy: float, road: tuple[float, float]) -> tuple[float, float]:
    """The velocity's part along a road's unit direction."""
    s = vx * road[0] + vy * road[1]
    return s * road[0], s * road[1]


def _unit(dx: float, dy: float) -> tuple[float, float]:
    n = math.hypot(dx, dy)
    return (dx / n, dy / n) if n > 0 else (0.0, 0.0)


def _state_dict(
    x: float, y: float, vx: float, vy: float, colour: str | None, road: str | None
) -> dict[str, Any]:
    return {
        "x": round(x, 2),
        "y": round(y, 2),
        "vx": round(vx, 2),
        "vy": round(vy, 2),
        "speed": round(math.hypot(vx, vy), 2),
        "colour": colour,
        "road": road,
    }


def anchoring_model(world: World) -> tuple[list[ObjectClass], list[LinkType]]:
    """The classes and links of the scenario: vision → world → on-road → car."""

    def colocate(vo: dict[str, Any]) -> dict[str, Any]:
        # the percept is relative to the UAV; its position at capture time anchors it
        pixel, heli = vo.get("pixel"), vo.get("heli")
        if pixel is None or heli is None:
            return {}
        x, y = heli[0] + pixel[0], heli[1] + pixel[1]
        return {
            "pos": (x, y, pixel[2]),  # with the capture time (world seconds)
            "on_road": world.road_at(x, y) is not None,
            "colour": vo["colour"],
        }

    classes = [
        ObjectClass(
            name="VisionObject",
            prefix="vo",
            features={
                "pixel": "vo/{id}/pixel",
                "heli": "vo/{id}/heli",
                "colour": "vo/{id}/colour",
                "confidence": "vo/{id}/confidence",
            },
            create="confidence > 0.5",
            create_from="camera/objects",
            maintain="confidence > 0.2",
        ),
        ObjectClass(
            name="WorldObject",
            prefix="car",
            features={
                "pos": "wo/{id}/pos",
                "on_road": "wo/{id}/on_road",
                "colour": "wo/{id}/colour",
            },
        ),
        ObjectClass(
            name="OnRoadObject",
            base="WorldObject",
            add="always[0,10] on_road",
            maintain="eventually[0,5] on_road",
        ),
        ObjectClass(name="Car", base="OnRoadObject", add="on_road"),
    ]
    links = [
        LinkType(
            name="vo2wo",
            from_class="VisionObject",
            to_class="WorldObject",
            establish="confidence > 0.5",
            maintain="a_confidence > 0.2",
            compute=colocate,
        )
    ]
    return classes, links


# -- the UAV's application ---------------------------------------------------------------------


class UavApplication:
    """The local DyKnow application of one UAV plus its handover logic (see the module)."""

    def __init__(self, platform: FederationPlatform, settings: UavSettings, world: World) -> None:
        self.platform = platform
        self.settings = settings
        self.world = world
        self.name = platform.name
        self.prefix = platform.name.replace("-", "_")
        # each road's direction (a unit vector): an asked-for car is predicted along it
        self._roads: dict[str | None, tuple[float, float]] = {
            r.id: _unit(r.b[0] - r.a[0], r.b[1] - r.a[1]) for r in world.roads
        }
        self.dk: DyKnowInstance = platform.instance
        self.area: int | None = None
        self.delegated_by: str | None = None
        self.world_start: float | None = None  # instance seconds when world time is 0
        self.camera: Camera | None = None
        self.assigned = asyncio.Event()
        self.sources: dict[str, Source] = {}
        self.tracks: dict[str, _Track] = {}
        self.relations = RelationChanges(world)
        self.last_states: dict[str, dict[str, Any]] = {}
        self.handovers: dict[str, dict[str, Any]] = {}  # object -> {to, label, state}
        self.anchored: dict[str, dict[str, Any]] = {}  # asked object -> {local, last, match}
        self.recognitions: list[Any] = []
        self.violations: list[dict[str, Any]] = []
        self.missed: dict[str, int] = {}  # percept -> detections missed in a row
        self.anchoring: Anchoring | None = None
        self.tasks: set[asyncio.Task[Any]] = set()
        self._tg: asyncio.TaskGroup | None = None
        self._stack: contextlib.AsyncExitStack | None = None  # holds the entered task group
        self.assignments: dict[int, str] = {}
        self.last_cars: list[str] = []
        self.local_now: set[str] = set()  # the cars our own camera tracks now
        self.fast_now: dict[str, bool] = {}
        self.speeding: list[dict[str, Any]] = []  # the speed monitor's violations
        self.flagged: set[str] = set()
        self.tracked = tracked_domain(self.dk)
        self.named: set[str] = set()  # federation names given to the DOM already

    # -- set-up ----------------------------------------------------------------------------
    def setup(self) -> None:
        """Sources, anchoring, chronicles: before joining the federation."""
        dk = self.dk
        for label in (
            "uav/self/position",
            "uav/self/max-speed",
            "uav/self/altitude",
            "uav/self/area",
            "camera/objects",
            "tracker/cars",
            "tracker/car-names",
            "tracker/fast",
            "chronicle/violations",
            *(f"relations/{r}" for r in RELATIONS),
            *(f"crossing/{e}" for e in CROSSING_EVENTS),
        ):
            self.sources[label] = dk.add_source(label)
        x, y, z = self.world.uav_position(self.settings.index, 0.0)
        self.sources["uav/self/max-speed"].push(self.max_speed)
        self.sources["uav/self/altitude"].push(z)
        self.sources["uav/self/position"].push({"x": x, "y": y, "z": z})
        classes, links = anchoring_model(self.world)
        self.anchoring = add_anchoring(dk, classes, links, period=PERIOD)
        for definition, inputs in CHRONICLES.values():
            proc = add_chronicle(dk, definition, inputs)
            dk.subscribe(proc.label, callback=self._on_recognitions)
        monitor = add_monitor(
            dk,
            SPEEDING,
            components={"Cars": "tracker/car-names", "fast": "tracker/fast"},
            period=PERIOD,
            name="monitor:speeding",
        )
        dk.subscribe(monitor.label, callback=self._on_verdicts)

    @property
    def max_speed(self) -> float:
        """This UAV's top speed (m/s): differs per UAV so the leader has something to weigh."""
        return 18.0 + 2.0 * self.settings.index

    def _on_recognitions(self, batch: list[tuple[Any, int, int]]) -> None:
        self.recognitions.extend(v for v, _, _ in batch)

    def _on_verdicts(self, batch: list[tuple[Any, int, int]]) -> None:
        for verdict, tv, _ in batch:
            if verdict.get("verdict") is False and self.world_start is not None:
                # the monitor restarts after a verdict: one report per car is enough
                fast = sorted(c for c, f in self.fast_now.items() if f and c not in self.flagged)
                self.flagged.update(fast)
                if fast:
                    t = round(self.world_time(tv), 2)
                    self.speeding.append({"t": t, "cars": fast})
                    self._report_speeding(fast, t, tv)

    def _report_speeding(self, cars: list[str], t: float, tv: int) -> None:
        """One ``violation`` sample per car flagged: the console lists them with the others."""
        for car in cars:
            where = self.last_states.get(car, {})
            value = {
                "kind": "speeding",
                "car": car,
                "other": None,
                "start": round(t - 2.0, 2),  # fast for the monitor's 2 s
                "end": t,
                "x": where.get("x"),
                "y": where.get("y"),
                "speed": where.get("speed"),
                "platform": self.name,
                "fused": False,
            }
            self.sources["chronicle/violations"].push(value, tv)

    async def __aenter__(self) -> Self:
        async with contextlib.AsyncExitStack() as stack:
            self._tg = await stack.enter_async_context(asyncio.TaskGroup())
            self._stack = stack.pop_all()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    def spawn(self, coro: Any, name: str) -> None:
        """Run ``coro`` as an owned task (cancelled at shutdown, failures logged)."""
        if self._tg is None:
            coro.close()
            raise RuntimeError(f"{self.name}: the application is not running (async with it)")
        task = self._tg.create_task(self._logged(coro, name), name=f"{self.name}:{name}")
        # cancelled before it ran, the wrapper never awaits ``coro``: close it then
        task.add_done_callback(lambda _: coro.close())
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def _logged(self, coro: Any, name: str) -> None:
        # one failing task (a handover) leaves the others running: logged, never raised
        try:
            await coro
        except Exception as exc:
            log.error("%s: task %s:%s failed: %r", self.name, self.name, name, exc)

    async def aclose(self) -> None:
        """Cancel every task this application started."""
        for task in list(self.tasks):
            task.cancel()
        stack, self._stack, self._tg = self._stack, None, None
        if stack is not None:
            await stack.aclose()

    # -- delegation ------------------------------------------------------------------------
    def cost_of(self, area: int) -> float:
        """Seconds to fly from here to ``area``'s centre at top speed."""
        a = self.world.areas[area]
        x, y, _ = self.world.uav_position(self.settings.index, 0.0)
        return math.hypot((a.x0 + a.x1) / 2 - x, (a.y0 + a.y1) / 2 - y) / self.max_speed

    def assign(self, area: int, world_start: float, delegated_by: str) -> None:
        """Monitor ``area`` from instance time ``world_start`` (world time 0)."""
        self.area = area
        self.world_start = world_start
        self.delegated_by = delegated_by
        self.camera = Camera(self.world, area, seed=self.settings.seed)
        self.assigned.set()
        self._publish_area()

    def _publish_area(self) -> None:
        if self.area is None:
            return
        a = self.world.areas[self.area]
        self.sources["uav/self/area"].push(
            {"index": self.area, "polygon": a.polygon(), "delegated-by": self.delegated_by}
        )

    def world_time(self, t_ns: int) -> float:
        """World (simulator) seconds at instance time ``t_ns``."""
        assert self.world_start is not None
        return t_ns / NS_PER_S - self.world_start

    # -- the running application ---------------------------------------------------------
    async def run(self) -> None:
        """Heli state always; camera and tracker once an area is assigned."""
        self.spawn(self._heli(), "heli")
        await self.assigned.wait()
        self.spawn(self._camera(), "camera")
        self.spawn(self._tracker(), "tracker")

    async def _heli(self) -> None:
        clock = self.dk.clock
        p = int(0.5 * NS_PER_S)
        due = -(-clock.now() // p) * p
        k = 0
        while True:
            await clock.sleep_until(due)
            wt = self.world_time(due) if self.world_start is not None else 0.0
            x, y, z = self.world.uav_position(self.settings.index, max(wt, 0.0))
            self.sources["uav/self/position"].push(
                {"x": round(x, 2), "y": round(y, 2), "z": round(z, 2)}, due
            )
            k += 1
            if k % 4 == 0:
                self._publish_area()
            due += p

    async def _camera(self) -> None:
        clock = self.dk.clock
        p = int(PERIOD * NS_PER_S)
        due = -(-clock.now() // p) * p
        camera = self.camera
        assert camera is not None
        while True:
            await clock.sleep_until(due)
            wt = self.world_time(due)
            if wt > self.settings.duration + 5:
                return
            if wt >= 0:
                self.sources["camera/objects"].push(self._percepts(camera, wt), due)
            due += p

    def _percepts(self, camera: Camera, wt: float) -> dict[str, Any]:
        ux, uy, _ = self.world.uav_position(self.settings.index, wt)
        heli = (round(ux, 3), round(uy, 3))
        out: dict[str, Any] = {}
        for vo in camera.observe(wt):
            # the capture time travels with the pixel: a world position is only as new
            # as the percept it was computed from
            pixel = (round(vo.x - ux, 3), round(vo.y - uy, 3), round(wt, 3))
            out[vo.vid] = {"pixel": pixel, "heli": heli, "colour": vo.colour, "confidence": 0.9}
            self.missed[vo.vid] = 0
        for vid in [v for v in self.missed if v not in out]:
            # a missed detection lowers the confidence; three in a row retire the percept
            n = self.missed[vid] = self.missed[vid] + 1
            out[vid] = {"confidence": 0.0 if n >= MISSES else 0.9 - 0.25 * n}
            if n >= MISSES:
                del self.missed[vid]
        return out

    async def _tracker(self) -> None:
        clock = self.dk.clock
        p = int(PERIOD * NS_PER_S)
        # half a period after the anchoring's grid point: its features are published
        due = -(-clock.now() // p) * p + p // 2
        k = 0
        while True:
            await clock.sleep_until(due)
            try:
                self.step(due, publish_cars=k % round(0.5 / PERIOD) == 0)
            except Exception:
                log.exception("%s: tracker step failed", self.name)
            k += 1
            due += p

    # -- one tracker step --------------------------------------------------------------------
    def step(self, t: int, *, publish_cars: bool) -> None:
        """States, relations, crossing events, handovers and violations at instance time t."""
        anch = self.anchoring
        assert anch is not None
        ts = t / NS_PER_S
        wt = self.world_time(t)
        states: dict[str, dict[str, Any]] = {}
        border = math.inf if self.area is None else self.world.areas[self.area].x1
        for wid in anch.members("WorldObject"):
            pos = self._valid_by(f"wo/{wid}/pos", t, FRESH)
            if pos is None:
                continue
            x, y, captured = pos.value
            if wt - captured > FRESH:
                continue
            track = self.tracks.setdefault(wid, _Track())
            track.add(captured, x, y)
            est = track.state(wt, self.world)
            if est is None:
                continue
            colour = self.dk.latest(f"wo/{wid}/colour").latest
            road = self.world.road_at(est[0], est[1])
            state = _state_dict(*est, None if colour is None else colour.value, road)
            obj = f"{self.prefix}_{wid}"
            if obj in self.handovers and est[0] > border:
                # past our border our camera sees it no more: the estimate is moved on
                # from its last points, in the lane it was last seen in, and would keep it
                # beside the other car after it cut in. The neighbour's states tell from here.
                continue
            states[obj] = state
            self._push(f"car/{obj}/state", state, t)
        self._feed_anchored(states, t)
        cars = {f"{self.prefix}_{c}" for c in anch.members("Car")}
        tracked = {o: s for o, s in states.items() if o in cars}
        self.last_cars = sorted(tracked)
        self._track(set(tracked), t)
        self.local_now = set(tracked)
        self.fast_now = {o: self._fast(s) for o, s in tracked.items()}
        self.sources["tracker/car-names"].push(self.last_cars, t)
        self.sources["tracker/fast"].push(self.fast_now, t)
        if publish_cars:
            self.sources["tracker/cars"].push(
                {
                    "cars": [
                        {"id": f"{self.name}/{o}", **{k: s[k] for k in _CAR_KEYS}}
                        for o, s in sorted(tracked.items())
                    ]
                },
                t,
            )
        for obj, h in self.handovers.items():
            fused = h.get("label")
            if obj in tracked or fused is None:
                continue
            s = self._valid_by(fused, t, FUSED_FRESH)
            if s is not None and ts - s.valid_time / NS_PER_S <= FUSED_FRESH:
                tracked[obj] = self._moved(s.value, ts - s.valid_time / NS_PER_S)
        self.last_states.update(tracked)
        self._relations(tracked, t)
        self._crossings(tracked, t)
        self._violations()

    def _valid_by(self, label: str, t: int, back: float) -> Sample | None:
        """The newest sample of ``label`` valid at or before ``t`` (the callers check its age).

        A step runs for its time ``t``, and on a busy machine late, catching up: by then
        samples valid after ``t`` may be in (the neighbour's states of a handed-over car,
        our anchoring's positions). Taken as the newest, a state from the step's future,
        moved back to ``t``, places a car where it only gets later: a reckless overtaker
        seen back in its lane while it is still beside, the overtake recognized seconds
        before it ends.
        """
        s = self.dk.latest(label).latest
        if s is None or s.valid_time <= t:
            return s
        older = self.dk.between(label, t - int(back * NS_PER_S), t).samples
        return older[-1] if older else None

    def _moved(self, state: dict[str, Any], dt: float) -> dict[str, Any]:
        """A fused state ``dt`` s old, moved on to the step's time as our tracker moves ours.

        Imported states come on a 0.5 s grid, and later still: taken as they are, a car
        handed over lags up to a second behind where it is (and behind the cars our own
        tracker places at the step's time), and its relations change that much later.
        Moved along its road, not sideways (`_Track.state`): the neighbour's sideways
        speed is as noisy as ours, and the cars are compared where both trackers saw them.
        """
        vx, vy = state["vx"], state["vy"]
        road = _road_direction(self.world, state["x"], state["y"], vx, vy)
        if road is not None:
            vx, vy = _along(vx, vy, road)
        x, y = state["x"] + vx * dt, state["y"] + vy * dt
        return {**state, "x": round(x, 2), "y": round(y, 2), "road": self.world.road_at(x, y)}

    def _track(self, now: set[str], t: int) -> None:
        """The `TRACKED` domain follows the cars tracked now (the label search's facts)."""
        for obj in sorted(now - self.local_now):
            if obj not in self.named:
                self.dk.objects.reserve(obj)
                self.named.add(obj)
            self.tracked.add(obj, time=t)
        for obj in sorted(self.local_now - now):
            self.tracked.discard(obj, time=t)

    def _push(self, label: str, value: Any, t: int) -> None:
        src = self.sources.get(label)
        if src is None:
            src = self.sources[label] = self.dk.add_source(label)
        src.push(value, t)

    def _relations(self, cars: dict[str, dict[str, Any]], t: int) -> None:
        for rel, a, b in self.relations.update(cars):
            self.sources[f"relations/{rel}"].push({"a": a, "b": b}, t)
            if rel in ("beside", "beside-fast"):
                self._maybe_hand_over(a, b, cars[a], cars[b])

    def _fast(self, state: dict[str, Any]) -> bool:
        return is_fast(state, self.world)

    def _crossings(self, cars: dict[str, dict[str, Any]], t: int) -> None:
        for obj, s in cars.items():
            wid = obj.removeprefix(f"{self.prefix}_")
            track = self.tracks.get(wid)
            if track is None:
                continue  # an imported (handed over) car: its crossings are its owner's
            event = crossing_step(track, s, self.world)
            if event is not None:
                kind, crossing = event
                self.sources[f"crossing/{kind}"].push({"car": obj, "crossing": crossing}, t)

    # -- violations --------------------------------------------------------------------------
    def _violations(self) -> None:
        if not self.recognitions:
            return
        found, self.recognitions = self.recognitions, []
        # a reckless overtake is also seen as beside (slow) by noise: report it once
        found.sort(key=lambda r: r.chronicle != "reckless-overtake")
        for rec in found:
            b = rec.bindings
            car, other = b.get("a", b.get("car")), b.get("b")
            end = max(rec.times.values()) / NS_PER_S
            start = min(rec.times.values()) / NS_PER_S
            if rec.chronicle != "turn":
                start = rec.times["beside"] / NS_PER_S
            if is_repeat(self.violations, rec.chronicle, car, other, end, end_key="end-instance"):
                continue
            where = self.last_states.get(str(car), {})
            value = {
                "kind": rec.chronicle,
                "car": car,
                "other": other,
                "start": round(start - (self.world_start or 0.0), 2),
                "end": round(end - (self.world_start or 0.0), 2),
                "x": where.get("x"),
                "y": where.get("y"),
                "platform": self.name,
                # states from the neighbour made it: a car out of our own view by now
                "fused": any(c in self.handovers and c not in self.local_now for c in (car, other)),
            }
            self.violations.append({**value, "end-instance": end})
            self.sources["chronicle/violations"].push(value, int(end * NS_PER_S))
            log.info("%s: %s", self.name, value)

    # -- handover: asking the neighbour -------------------------------------------------------
    def _neighbour(self) -> str | None:
        if self.area is None or self.area + 1 >= len(self.world.areas):
            return None
        return self.assignments.get(self.area + 1)

    def _maybe_hand_over(self, a: str, b: str, sa: dict[str, Any], sb: dict[str, Any]) -> None:
        if self.area is None:
            return
        border = self.world.areas[self.area].x1
        neighbour = self._neighbour()
        if neighbour is None or sa["vx"] <= 0 or border - sa["x"] > HANDOVER_RANGE:
            return
        for obj in (a, b):
            if obj not in self.handovers and obj.startswith(self.prefix + "_"):
                self.handovers[obj] = {"to": neighbour, "asked": time.monotonic()}
                self.spawn(self._hand_over(obj, neighbour), f"handover:{obj}")

    async def _hand_over(self, obj: str, neighbour: str) -> None:
        semantic = f"{obj}-state"
        fed = self.platform.federation_agent
        h = self.handovers[obj]
        try:
            h["export"] = await fed.create_stream(
                neighbour, [semantic], sample_period=0.5, timeout=10.0
            )
            h["agreed"] = time.monotonic()
            fusion = await self.platform.fuse(
                semantic, neighbour, f"fused/{obj}/state", window=0.3, timeout=60.0
            )
            h["label"] = fusion.label
            h["first-import"] = time.monotonic()
            log.info("%s: %s handed over to %s", self.name, obj, neighbour)
        except Exception as exc:
            h["error"] = str(exc)
            log.warning("%s: handover of %s to %s failed: %s", self.name, obj, neighbour, exc)

    # -- handover: asked by the neighbour ------------------------------------------------------
    async def anchor_object(self, semantic: str, local: str, requester: str) -> bool:
        """Anchor another UAV's object: its trajectory, then look for it among ours."""
        m = OBJECT_STATE.fullmatch(semantic)
        if m is None or self.anchoring is None:
            return False
        fed = self.platform.federation_agent
        answer = await fed.request_from(
            requester,
            {"action": "get-trajectory", "labels": [semantic], "from": -120, "relative": True},
            timeout=5.0,
        )
        samples = answer.get(semantic, {}).get("samples", [])
        if not samples:
            return False
        value, valid = samples[-1][0], samples[-1][1]
        if local not in self.sources:
            self.sources[local] = self.dk.add_source(local)
        self.anchored[m.group(1)] = {
            "local": local,
            "last": value,
            "valid": float(valid),
            "trajectory": len(samples),
            "from": requester,
            "match": None,
            "asked": time.monotonic(),
        }
        log.info(
            "%s: anchoring %s from %s (%d samples)", self.name, semantic, requester, len(samples)
        )
        return True

    def _feed_anchored(self, states: dict[str, dict[str, Any]], t: int) -> None:
        for a in self.anchored.values():
            match = a["match"]
            if match is None or match not in states:
                # not seen this step (gone, or its state late on a busy machine): look
                # again, and keep the old match when nothing else fits
                found = self._find(a, states, t)
                if found is not None and found != match:
                    match = a["match"] = found
                    a.setdefault("matched", time.monotonic())
                    log.info("%s: anchored %s as our %s", self.name, a["local"], match)
            if match is not None and match in states:
                self.sources[a["local"]].push(states[match], t)

    def _find(self, a: dict[str, Any], states: dict[str, dict[str, Any]], t: int) -> str | None:
        """The object tracked now whose first sighting here fits the asker's last state.

        Each candidate is compared where our camera first saw it after that state (its
        position's capture time), not where it is now nor where our tracker first placed
        it: both come later the busier this process, and the asker's answer later the
        busier the machine. The state is moved on along its road, not sideways: a car
        asked about during a lane change (the reckless overtaker swerving out) stays on
        its road, while its lane-change speed carried on for 5 s puts it 13 m off.
        """
        last, valid = a["last"], a["valid"]
        start = self.world_start or 0.0
        since = min(int(valid * NS_PER_S), t)
        first: dict[str, tuple[float, float, float]] = a.setdefault("first", {})
        vx, vy = last["vx"], last["vy"]
        road = self._roads.get(last.get("road"))
        if road is not None:  # the velocity along the road only
            along = vx * road[0] + vy * road[1]
            vx, vy = along * road[0], along * road[1]
        best, best_d = None, MATCH
        for obj, s in states.items():
            if last.get("colour") is not None and s.get("colour") != last["colour"]:
                continue
            seen = first.get(obj)
            if seen is None:
                wid = obj[len(self.prefix) + 1 :]
                # its positions since then, oldest first (one at least: it is tracked)
                samples = self.dk.between(f"wo/{wid}/pos", since, t).samples
                if not samples:
                    continue
                x, y, captured = samples[0].value
                seen = first[obj] = (start + captured, x, y)
            ts, x, y = seen
            dt = ts - valid
            d = math.hypot(x - (last["x"] + vx * dt), y - (last["y"] + vy * dt))
            if d < best_d:
                best, best_d = obj, d
        return best

    # -- the report ----------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        """A short progress line's worth: area, cars now, violations so far."""
        return {
            "area": self.area,
            "world-time": None
            if self.world_start is None
            else round(self.world_time(self.dk.clock.now()), 1),
            "cars": len(self.last_cars),
            "violations": len(self.violations),
            "speeding": len(self.speeding),
            "handovers": len(self.handovers),
            "anchored": sum(1 for a in self.anchored.values() if a["match"] is not None),
        }

    def report(self) -> dict[str, Any]:
        """What this UAV did, for the demo's final report."""
        stats = self.platform.agents.stats
        metrics = self.dk.metrics()
        delays = [
            [m.get("delay_p50"), m.get("delay_p99")]
            for label, m in metrics.items()
            if label.startswith("import/")
        ]
        return {
            "name": self.name,
            "area": self.area,
            "delegated-by": self.delegated_by,
            "violations": [
                {k: v for k, v in x.items() if k != "end-instance"} for x in self.violations
            ],
            "cars-tracked": len(self.tracks),
            "speeding": self.speeding,
            "handovers": {
                o: {k: v for k, v in h.items() if k in ("to", "export", "error")}
                | {
                    "agreed-after": _since(h, "agreed"),
                    "first-import-after": _since(h, "first-import"),
                }
                for o, h in self.handovers.items()
            },
            "anchored": {
                o: {
                    "from": a["from"],
                    "trajectory": a["trajectory"],
                    "match": a["match"],
                    "matched-after": _since(a, "matched"),
                }
                for o, a in self.anchored.items()
            },
            "exports": len(self.platform.federation_agent.exports),
            "imports": sum(1 for label in metrics if label.startswith("import/")),
            "acl": {"sent": stats.sent_remote, "received": stats.received_remote},
            "import-delay": delays,
        }


_CAR_KEYS = ("x", "y", "speed", "colour", "road")


def _since(d: dict[str, Any], key: str) -> float | None:
    if key not in d:
        return None
    return round(float(d[key]) - float(d["asked"]), 3)


# -- the agent -----------------------------------------------------------------------------


class TrafficMonitor(Agent):
    """The UAV's monitoring service: leads the delegation, or bids for an area."""

    def __init__(self, app: UavApplication) -> None:
        super().__init__("traffic")
        self.app = app

    async def setup(self) -> None:
        """Listed in the global directory: the leader finds the UAVs through it."""
        assert self.platform.df is not None
        await self.platform.df.register(
            ServiceDescription(
                name="traffic-monitoring",
                type=SERVICE_TYPE,
                provider=self.aid,
                visibility=Visibility.PUBLIC,
            )
        )

    @on_request(ONTOLOGY, concurrent=True)
    async def _monitor(self, message: ACLMessage) -> Any:
        """``monitor`` (the leader's job: delegation), ``status`` or ``report``."""
        content = message.content
        action = content.get("action") if isinstance(content, dict) else None
        if action == "monitor":
            assert isinstance(content, dict)  # action is only set for a dict
            uavs = content.get("uavs", [])
            if not isinstance(uavs, list):
                raise Refuse("'uavs' must be a list of platform names")
            names = [u for u in uavs if isinstance(u, str)]
            if len(names) != len(uavs):
                raise Refuse("'uavs' must be a list of platform names")
            return await self.delegate(names)
        if action == "status":
            return self.app.status()
        if action == "report":
            return self.app.report()
        raise Refuse(f"unknown action {action!r} (monitor, status or report)")

    async def delegate(self, uavs: Iterable[str] = ()) -> dict[str, Any]:
        """Global request for capabilities, then one Contract-Net per area.

        ``uavs``: the platforms the operator saw join; the leader waits (bounded) until they
        are members here too (`await_members`), since each platform learns the members by
        itself and a UAV not yet a member here would be neither asked nor given an area.
        """
        app = self.app
        fed = app.platform.federation_agent
        if missing := await await_members(app.platform, uavs, MEMBERS_WAIT):
            log.warning("%s: delegating without %s (not members here)", self, sorted(missing))
        # The request returns as soon as every member answered: the deadline only bounds
        # the wait for one that cannot (a first request to a member agrees a session first,
        # slow on a loaded machine)
        caps = await fed.global_request(
            {"action": "get-latest", "labels": ["heli-max-speed", "heli-altitude"]},
            deadline=CAPABILITIES_DEADLINE,
        )
        gdf = self.platform.global_df
        assert gdf is not None
        participants = sorted(
            {s.provider for s in gdf.search(type=SERVICE_TYPE)} | {self.aid},
        )
        world_start = app.dk.clock.now() / NS_PER_S + max(2.0, 2.0 * app.settings.speed)
        assignments: dict[int, str] = {}
        for area in range(len(app.world.areas)):
            result = await contract_net(
                self,
                participants,
                {"task": "monitor-area", "area": area, "start": world_start},
                deadline=2.0,
                select=_cheapest,
                ontology=ONTOLOGY,
            )
            for p in result.accepted:
                assignments[area] = p.participant.split("@", 1)[1]
                participants.remove(p.participant)
        # everyone learns who watches which area (the handover needs its neighbour)
        for aid in {f"traffic@{p}" for p in assignments.values()}:
            try:
                await self.send(
                    self.message(
                        Performative.INFORM,
                        aid,
                        {"assignments": {str(k): v for k, v in assignments.items()}},
                        ontology=ONTOLOGY,
                    )
                )
            except Exception as exc:  # one traffic agent gone must not stop the delegation
                log.warning("%s: telling %s the assignments failed: %s", self, aid, exc)
        return {
            "assignments": {str(k): v for k, v in assignments.items()},
            "start": world_start,
            "capabilities": {p: a for p, a in caps.answers.items()},
            "silent": caps.no_answer,
            "unlisted": caps.unlisted,
            "refused": caps.refused,
        }

    @on_cfp(ONTOLOGY)
    async def _bid(self, cfp: ACLMessage) -> Any:
        """Bid the flying time to the area; refuse when already monitoring one."""
        c: Any = cfp.content
        if not isinstance(c, dict) or not isinstance(c.get("area"), int):
            raise Refuse("expected {'task': 'monitor-area', 'area': int}")
        if self.app.area is not None:
            raise Refuse(f"monitoring area {self.app.area} already")
        if not 0 <= c["area"] < len(self.app.world.areas):
            raise Refuse(f"no area {c['area']}")
        start = c.get("start")
        if not isinstance(start, (int, float)):
            raise Refuse("expected the world's start time ('start')")
        return {"area": c["area"], "cost": round(self.app.cost_of(c["area"]), 3), "start": start}

    @on_accept_proposal(ONTOLOGY)
    async def _accepted(self, message: ACLMessage) -> Any:
        """Monitor the area from the leader's world start."""
        c: Any = message.content  # our own proposal, accepted
        assert isinstance(c, dict)
        self.app.assign(int(c["area"]), float(c["start"]), platform_of(message.sender))
        return {"monitoring": c["area"]}

    @on(MessageTemplate(Performative.INFORM, ontology=ONTOLOGY))
    async def _assignments(self, message: ACLMessage) -> None:
        """Who watches which area: the leader tells everyone once all are delegated."""
        c: Any = message.content
        if isinstance(c, dict) and isinstance(c.get("assignments"), dict):
            self.app.assignments = {int(k): str(v) for k, v in c["assignments"].items()}


async def await_members(
    platform: FederationPlatform, names: Iterable[str], timeout: float
) -> set[str]:
    """Wait until every one of ``names`` is a member of ``platform`` (at most ``timeout`` s);
    the rest.

    A member by its signed events, as `members` says: its services count from then on (a
    global request asks it, a search finds it), even while its first signed snapshot is
    asked and it is not listed yet (`GlobalDirectory.listed`, what a stream receiver must
    be: none of the delegation's)."""
    expected = set(names) - {platform.name}
    if not expected <= set(platform.members):
        with contextlib.suppress(TimeoutError):
            async with platform.membership() as events, asyncio.timeout(timeout):
                # listed by now, or between the check above and the subscription
                while not expected <= set(platform.members):
                    await events.get()
    return expected - set(platform.members)


def _cheapest(proposals: list[Proposal]) -> list[Proposal]:
    if not proposals:
        return []
    return [min(proposals, key=lambda p: (_cost(p), p.participant))]


def _cost(p: Proposal) -> float:
    c: Any = p.content
    return float(c["cost"]) if isinstance(c, dict) and "cost" in c else math.inf


# -- the process -----------------------------------------------------------------------------


def run_uav(settings: UavSettings) -> None:
    """A UAV process's main: run until SIGTERM/SIGINT, then write its report."""
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(message)s")
    asyncio.run(_main(settings))


async def _main(settings: UavSettings) -> None:
    config = PlatformConfig.from_dict(settings.config, source=settings.name)
    world = World.generate(settings.seed, settings.n_uavs, settings.duration)
    clock = SimClock(settings.t0_wall_ns, settings.speed)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    parent = multiprocessing.parent_process()
    if parent is not None:  # the launcher killed without a word: do not outlive it
        loop.add_reader(parent.sentinel, stop.set)
    app_box: list[UavApplication] = []

    async def anchor(semantic: str, local: str, requester: str) -> bool:
        return await app_box[0].anchor_object(semantic, local, requester)

    instance = DyKnowInstance(config.name, clock=clock)
    tracked_domain(instance)  # the fact feed follows it from the platform's start
    async with (
        instance,
        FederationPlatform(
            config, instance=instance, join=False, anchor=anchor, rules=fact_rules()
        ) as platform,
    ):
        app = UavApplication(platform, settings, world)
        app_box.append(app)
        app.setup()
        await platform.agents.add(TrafficMonitor(app))
        await platform.join()
        settle_gc()
        async with app:
            app.spawn(app.run(), "run")
            await stop.wait()
