"""The traffic demo's simulated world: roads, cars, scripted violations and a noisy camera.

Every UAV process builds its own copy with ``World.generate(seed, n_uavs, duration)``; the
same arguments give the same world in every process, so no world state travels between
processes. Everything is a pure function of simulated time ``t`` (seconds since the start).

The map: a strip ``600 * n_uavs`` m wide and 400 m high, one area of responsibility per UAV
(vertical strips, index 0 at the west). A two-lane main road ``r1`` runs east-west at
y = 200 through every area; each area has one north-south road (``r2``, ``r3``, ...) that
crosses it in a crossing (``c1``, ``c2``, ...). Cars drive east in the southern lane of
``r1``; the northern lane is for overtaking (3.5 m to the side). One car is parked off-road.

The scripted events (what ``ground_truth`` lists), for ``n_uavs >= 2`` and ``duration >= 60``:

1. ``overtake``: in area 0 a car at (or under) the limit passes a ``slow`` car.
2. ``reckless-overtake``: the handover case. It starts in area ``k = n_uavs - 2`` at least
   25 m before the border with area ``k + 1`` and ends at least 25 m beyond it; the
   overtaker drives faster than 1.3 x the limit while beside. Both cars then stay in area
   ``k + 1`` for at least 8 s.
3. ``turn``: a car on ``r1`` turns onto the north-south road in one area's crossing.

Plus 3-6 ``normal`` cars, spaced so that no two cars outside a scripted pair are ever within
40 m of each other (so nothing else looks like an overtake). Every car in an event is on a
road inside the event's start area for at least 12 s before the event starts (the UAVs'
trackers promote an on-road object to a car after 10 s). All events end before
``duration - 10``.

Smaller cases: with ``n_uavs == 1`` there is no border and so no reckless overtake (the
legal overtake and the turn happen in area 0). An event that cannot fit into ``duration``
(it needs ~14 s of lead-in and must end before ``duration - 10``) is left out: below about
40 s some events are missing, below about 28 s there are none, only normal traffic.
``ground_truth`` always lists exactly what was produced.

An overtake starts when the overtaker is first *beside* the other car (in the other lane,
less than ``BESIDE_DISTANCE`` m behind or ahead) and ends when it is back in the lane,
ahead. Before it the overtaker is seen in the lane behind, within 40 m; at its end it is
15-36 m in front. A turn starts when the car enters the crossing's circle and ends when it
leaves it. ``CarTruth.behaviour`` says what a car is doing at that instant (``overtaking``,
``reckless`` or ``turning`` only during its event); the parked car stands in a parking lot
(``World.parking``, also in ``to_dict()``) with ``road`` None.

The camera sees every car inside its area (borders included). Its track ids (``vid``) are
numbered by the start of each stay in view, so they depend on ``t`` alone: a car keeps its
vid while it stays in view (missed detections included) and gets a new one if it comes
back. No generated car leaves an area and comes back, so each car has one vid per camera.

Where it lies: the map's origin (0, 0) is `ANCHOR`, a real place (Linköping University's
campus, where DyKnow was built), x east and y north of it. ``World.lat_lon`` gives a map
point's latitude and longitude; the operator's ``[foxglove] origin`` is `ANCHOR`, so its
Foxglove map draws the UAVs and cars there (docs/foxglove.md).
"""

from __future__ import annotations

import math
import random
from bisect import bisect_right
from collections.abc import Callable
from dataclasses import dataclass

from .._geo import local_to_geo

__all__ = [
    "ANCHOR",
    "AREA_WIDTH",
    "BESIDE_DISTANCE",
    "LANE_WIDTH",
    "Area",
    "Camera",
    "CarTruth",
    "Crossing",
    "Road",
    "Violation",
    "VisionObject",
    "World",
]

AREA_WIDTH = 600.0
WORLD_HEIGHT = 400.0
MAIN_Y = 200.0
LANE_WIDTH = 3.5
BESIDE_DISTANCE = 8.0
CROSSING_RADIUS = 12.0
UAV_ALTITUDE = 60.0
MAX_UAVS = 32
ANCHOR = (58.3975, 15.5765)
"""Latitude and longitude (degrees) of the map's origin: Linköping University (Valla)."""

_DRIVE_Y = MAIN_Y - LANE_WIDTH / 2  # eastbound traffic keeps to the southern (right) lane
_PASS_Y = MAIN_Y + LANE_WIDTH / 2
_LANE_CHANGE_S = 2.5
_LEAD_IN_S = 14.0  # 12 s on road before an event, plus slack for the trackers
_CLEARANCE = 45.0  # checked on a 0.25 s grid, so the true minimum stays above 40 m
_CHECK_DT = 0.25
_COLOURS = (
    "red",
    "blue",
    "white",
    "black",
    "silver",
    "green",
    "yellow",
    "orange",
    "brown",
    "purple",
)

_LINE = 0
_ARC = 1


@dataclass(frozen=True, slots=True)
class Road:
    """A straight road segment with lanes and a speed limit (m/s)."""

    id: str
    a: tuple[float, float]
    b: tuple[float, float]
    speed_limit: float
    lanes: int = 2


@dataclass(frozen=True, slots=True)
class Crossing:
    """Where roads meet: a circle around their intersection."""

    id: str
    x: float
    y: float
    radius: float
    roads: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class Area:
    """One UAV's area of responsibility: an axis-aligned rectangle (borders included)."""

    index: int
    x0: float
    y0: float
    x1: float
    y1: float

    def contains(self, x: float, y: float) -> bool:
        """Whether (x, y) lies in the area."""
        return self.x0 <= x <= self.x1 and self.y0 <= y <= self.y1

    def polygon(self) -> list[list[float]]:
        """The 4 corners, counter-clockwise from the south-west, as JSON-ready lists."""
        return [[self.x0, self.y0], [self.x1, self.y0], [self.x1, self.y1], [self.x0, self.y1]]


@dataclass(frozen=True, slots=True)
class CarTruth:
    """The ground truth of one car at one instant."""

    id: str
    x: float
    y: float
    vx: float
    vy: float
    speed: float
    road: str | None
    colour: str
    behaviour: str


@dataclass(frozen=True, slots=True)
class Violation:
    """A scripted event the simulator knows happened (the ground truth to score UAVs by)."""

    kind: str
    car: str
    other: str | None
    start: float
    end: float
    start_area: int
    end_area: int
    x: float
    y: float


@dataclass(frozen=True, slots=True)
class VisionObject:
    """One noisy detection by one UAV's camera; ``vid`` is the camera's own track id."""

    vid: str
    x: float
    y: float
    colour: str


# A leg is one piece of a car's path: (t0, kind, p1..p6, road, behaviour).
# Line: x = p1 + p3*dt + p5*dt²/2, y = p2 + p4*dt + p6*dt²/2 (constant acceleration).
# Arc: centre (p1, p2), radius p3, angle p4 at t0, angular speed p5 (rad/s).
_Leg = tuple[float, int, float, float, float, float, float, float, str | None, str]


class _Car:
    """One car's whole path (piecewise legs) and when it is inside the world."""

    __slots__ = ("colour", "id", "legs", "starts", "t_in", "t_out")

    def __init__(self, legs: list[_Leg], colour: str) -> None:
        self.id = ""
        self.colour = colour
        self.legs = legs
        self.starts = [leg[0] for leg in legs]
        self.t_in = -math.inf
        self.t_out = math.inf

    def state(self, t: float) -> tuple[float, float, float, float, str | None, str]:
        """Position, velocity, road and behaviour at t (first/last legs extend forever)."""
        i = bisect_right(self.starts, t) - 1
        t0, kind, p1, p2, p3, p4, p5, p6, road, behaviour = self.legs[i if i > 0 else 0]
        dt = t - t0
        if kind == _LINE:
            return (
                p1 + p3 * dt + 0.5 * p5 * dt * dt,
                p2 + p4 * dt + 0.5 * p6 * dt * dt,
                p3 + p5 * dt,
                p4 + p6 * dt,
                road,
                behaviour,
            )
        angle = p4 + p5 * dt
        c, s = math.cos(angle), math.sin(angle)
        return p1 + p3 * c, p2 + p3 * s, -p3 * p5 * s, p3 * p5 * c, road, behaviour

    def xy(self, t: float) -> tuple[float, float]:
        """Position at t."""
        x, y, _, _, _, _ = self.state(t)
        return x, y

    def clip_to(self, width: float, height: float) -> None:
        """Work out when the car enters and leaves the world (first/last legs are straight)."""
        first, last = self.legs[0], self.legs[-1]
        lo, _ = _ray_inside(first, width, height)
        _, hi = _ray_inside(last, width, height)
        self.t_in, self.t_out = first[0] + lo, last[0] + hi


def _ray_inside(leg: _Leg, width: float, height: float) -> tuple[float, float]:
    """The times (relative to the leg's start) when a straight leg's line is in the world."""
    _, kind, x, y, vx, vy, ax, ay, _, _ = leg
    assert kind == _LINE and ax == 0 and ay == 0, "first and last legs must be straight"
    lo, hi = -math.inf, math.inf
    for p, v, top in ((x, vx, width), (y, vy, height)):
        if v == 0:
            if not 0 <= p <= top:
                return math.inf, -math.inf
            continue
        a, b = (0 - p) / v, (top - p) / v
        lo, hi = max(lo, min(a, b)), min(hi, max(a, b))
    return lo, hi


class _Path:
    """Builds a car's legs one after the other from a starting state."""

    def __init__(self, t: float, x: float, y: float, vx: float, vy: float = 0.0) -> None:
        self.t, self.x, self.y, self.vx, self.vy = t, x, y, vx, vy
        self.legs: list[_Leg] = []

    def go(
        self,
        duration: float,
        road: str | None,
        behaviour: str,
        *,
        vx: float | None = None,
        vy: float | None = None,
        ax: float = 0.0,
        ay: float = 0.0,
    ) -> _Path:
        """A leg of constant acceleration; vx/vy set the velocity at its start."""
        if vx is not None:
            self.vx = vx
        if vy is not None:
            self.vy = vy
        self.legs.append((self.t, _LINE, self.x, self.y, self.vx, self.vy, ax, ay, road, behaviour))
        d = duration
        self.x += self.vx * d + 0.5 * ax * d * d
        self.y += self.vy * d + 0.5 * ay * d * d
        self.vx += ax * d
        self.vy += ay * d
        self.t += d
        return self

    def arc(
        self,
        centre: tuple[float, float],
        r: float,
        angle: float,
        omega: float,
        duration: float,
        road: str | None,
        behaviour: str,
    ) -> _Path:
        """A leg on a circle around ``centre`` starting at ``angle``, turning at ``omega``."""
        cx, cy = centre
        self.legs.append((self.t, _ARC, cx, cy, r, angle, omega, 0.0, road, behaviour))
        end = angle + omega * duration
        self.x, self.y = cx + r * math.cos(end), cy + r * math.sin(end)
        self.vx, self.vy = -r * omega * math.sin(end), r * omega * math.cos(end)
        self.t += duration
        return self

    def car(self, colour: str, road: str | None, behaviour: str) -> _Car:
        """Finish with an open straight leg at the current velocity."""
        self.legs.append(
            (self.t, _LINE, self.x, self.y, self.vx, self.vy, 0.0, 0.0, road, behaviour)
        )
        return _Car(self.legs, colour)


@dataclass(slots=True)
class _Event:
    """A scripted event under construction: its cars (by role) and its times."""

    kind: str
    car: _Car
    other: _Car | None
    start: float
    end: float


class _Rejected(Exception):
    """A sampled plan broke a rule; the generator draws again."""


class World:
    """The deterministic simulated world every UAV process runs its own copy of."""

    def __init__(self, seed: int, n_uavs: int = 3, duration: float = 60.0) -> None:
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ValueError(f"seed must be an int, not {seed!r}")
        if isinstance(n_uavs, bool) or not isinstance(n_uavs, int):
            raise ValueError(f"n_uavs must be an int, not {n_uavs!r}")
        if not 1 <= n_uavs <= MAX_UAVS:
            raise ValueError(f"n_uavs must be between 1 and {MAX_UAVS}, not {n_uavs}")
        if isinstance(duration, bool) or not isinstance(duration, int | float):
            raise ValueError(f"duration must be a number of seconds, not {duration!r}")
        if not (math.isfinite(duration) and duration > 0):
            raise ValueError(f"duration must be a positive number of seconds, not {duration}")
        self.seed = seed
        self.anchor = ANCHOR
        self.n_uavs = n_uavs
        self.duration = float(duration)
        self.width = AREA_WIDTH * n_uavs
        self.height = WORLD_HEIGHT
        rng = random.Random(seed)
        self.roads, self.crossings = _road_network(rng, n_uavs)
        self.areas = tuple(
            Area(i, AREA_WIDTH * i, 0.0, AREA_WIDTH * (i + 1), WORLD_HEIGHT) for i in range(n_uavs)
        )
        self.parking: tuple[tuple[float, float, float, float], ...] = ()
        self._limits = {road.id: road.speed_limit for road in self.roads}
        self._cars: list[_Car] = []
        self._truth: list[Violation] = []
        for _attempt in range(400):
            try:
                self._populate(rng)
                break
            except _Rejected:
                continue
        else:  # pragma: no cover - the sampling windows make this practically unreachable
            raise RuntimeError(f"could not lay out a traffic scenario for seed {seed}")

    @classmethod
    def generate(cls, seed: int, n_uavs: int = 3, duration: float = 60.0) -> World:
        """The world for this seed, number of UAVs (areas) and duration (seconds)."""
        return cls(seed, n_uavs, duration)

    # --- queries ------------------------------------------------------------------------

    def cars_at(self, t: float) -> list[CarTruth]:
        """The cars inside the world at t (a pure function of t)."""
        out = []
        for car in self._cars:
            if car.t_in <= t <= car.t_out:
                x, y, vx, vy, road, behaviour = car.state(t)
                speed = math.hypot(vx, vy)
                out.append(CarTruth(car.id, x, y, vx, vy, speed, road, car.colour, behaviour))
        return out

    def ground_truth(self) -> list[Violation]:
        """Every scripted event in [0, duration], sorted by end time."""
        return list(self._truth)

    def road_at(self, x: float, y: float, tolerance: float = 6.0) -> str | None:
        """The GIS: the nearest road within ``tolerance`` m of (x, y), or None."""
        best, best_d = None, tolerance
        for road in self.roads:
            d = _segment_distance(x, y, road.a, road.b)
            if d <= best_d and (best is None or d < best_d):
                best, best_d = road.id, d
        return best

    def crossing_at(self, x: float, y: float) -> str | None:
        """The crossing whose circle contains (x, y), or None."""
        for c in self.crossings:
            if (x - c.x) ** 2 + (y - c.y) ** 2 <= c.radius * c.radius:
                return c.id
        return None

    def area_of(self, x: float, y: float) -> int | None:
        """The index of the area containing (x, y) (on a border, the eastern one), or None."""
        if not (0 <= y <= self.height and 0 <= x <= self.width):
            return None
        return min(int(x // AREA_WIDTH), self.n_uavs - 1)

    def speed_limit(self, road: str) -> float:
        """A road's speed limit in m/s."""
        try:
            return self._limits[road]
        except KeyError:
            raise ValueError(f"unknown road {road!r}; roads are {sorted(self._limits)}") from None

    def uav_position(self, index: int, t: float) -> tuple[float, float, float]:
        """Where UAV ``index`` hovers at t: a slow 40 m circle over its area's centre, z up."""
        area = self._area(index)
        angle = 2 * math.pi * (t / 120.0 + index / max(self.n_uavs, 1))
        cx, cy = (area.x0 + area.x1) / 2, (area.y0 + area.y1) / 2
        return cx + 40.0 * math.cos(angle), cy + 40.0 * math.sin(angle), UAV_ALTITUDE

    def border(self, k: int) -> float:
        """The x of the border between areas k and k + 1."""
        if not 0 <= k < self.n_uavs - 1:
            raise ValueError(f"there is no border after area {k} with {self.n_uavs} areas")
        return AREA_WIDTH * (k + 1)

    def lat_lon(self, x: float, y: float) -> tuple[float, float]:
        """The latitude and longitude (degrees) of map point (x, y): `ANCHOR` is (0, 0)."""
        return local_to_geo(self.anchor, x, y)

    def to_dict(self) -> dict[str, object]:
        """The JSON-ready map for the operator console."""
        return {
            "seed": self.seed,
            "width": self.width,
            "height": self.height,
            "duration": self.duration,
            "roads": [
                {
                    "id": r.id,
                    "a": list(r.a),
                    "b": list(r.b),
                    "speed_limit": r.speed_limit,
                    "lanes": r.lanes,
                }
                for r in self.roads
            ],
            "crossings": [
                {"id": c.id, "x": c.x, "y": c.y, "radius": c.radius, "roads": list(c.roads)}
                for c in self.crossings
            ],
            "areas": [{"index": a.index, "polygon": a.polygon()} for a in self.areas],
            "parking": [
                [[x0, y0], [x1, y0], [x1, y1], [x0, y1]] for x0, y0, x1, y1 in self.parking
            ],
        }

    def _area(self, index: int) -> Area:
        if isinstance(index, bool) or not isinstance(index, int):
            raise ValueError(f"area index must be an int, not {index!r}")
        if not 0 <= index < self.n_uavs:
            raise ValueError(f"area index must be in 0..{self.n_uavs - 1}, not {index}")
        return self.areas[index]

    # --- the scenario -------------------------------------------------------------------

    def _populate(self, rng: random.Random) -> None:
        """Sample one scenario; raise _Rejected when it breaks a rule."""
        limit = self._limits["r1"]
        cruise = limit * rng.uniform(0.82, 0.95)
        palette = list(_COLOURS)
        rng.shuffle(palette)
        # Every moving car has left the world by then (the slowest crosses it at half the limit).
        horizon = min(self.duration, (self.width + 300.0) / (0.5 * limit) + 60.0)
        grid = [i * _CHECK_DT for i in range(int(horizon / _CHECK_DT) + 1)]
        events: list[_Event] = []
        cars: list[_Car] = []
        tracks: list[list[tuple[float, float] | None]] = []
        makers = []
        # The most constrained event first; each later one is fitted around the ones before.
        if self.n_uavs >= 2:
            makers.append(lambda: self._reckless_overtake(rng, limit, cruise))
        makers.append(lambda: self._legal_overtake(rng, limit, cruise))
        makers.append(lambda: self._turn(rng, cruise))
        for make in makers:
            for _try in range(40):
                try:
                    ev = make()
                except _Rejected:
                    continue
                if ev is None:  # it cannot fit into this duration
                    break
                new = [car for car in (ev.car, ev.other) if car is not None]
                for car in new:
                    car.clip_to(self.width, self.height)
                new_tracks = [_track(car, grid) for car in new]
                if any(_too_close(a, b) for a in new_tracks for b in tracks):
                    continue
                events.append(ev)
                cars += new
                tracks += new_tracks
                break
            else:
                if self.duration >= 60.0:
                    raise _Rejected
                # A short world may do without this event rather than fail.

        # The handover pair's colours are theirs alone, so the UAVs can tell them apart.
        reserved = []
        for ev in events:
            if ev.kind == "reckless-overtake" and ev.other is not None:
                ev.car.colour, ev.other.colour = palette[0], palette[1]
                reserved = palette[:2]
        free = [c for c in palette if c not in reserved]
        for ev in events:
            for member in (ev.car, ev.other):
                if member is not None and not member.colour:
                    member.colour = rng.choice(free)

        wanted = rng.randint(3, 6)
        placed = 0
        for _try in range(80):
            if placed == wanted:
                break
            x0 = rng.uniform(-150.0, self.width - 60.0)
            car = _Path(0.0, x0, _DRIVE_Y, cruise).car(rng.choice(free), "r1", "normal")
            car.clip_to(self.width, self.height)
            if car.t_in > self.duration - 10 or car.t_out < 5:
                continue
            track = _track(car, grid)
            if any(_too_close(track, other) for other in tracks):
                continue
            cars.append(car)
            tracks.append(track)
            placed += 1
        if placed < 3:
            raise _Rejected

        lot_area = rng.randrange(self.n_uavs)
        crossing = self.crossings[lot_area]
        side = rng.choice((-1.0, 1.0))
        lx = crossing.x + side * rng.uniform(60.0, 200.0)
        ly = MAIN_Y + rng.choice((-1.0, 1.0)) * rng.uniform(60.0, 150.0)
        self.parking = ((lx - 20.0, ly - 15.0, lx + 20.0, ly + 15.0),)
        parked = _Path(0.0, lx + rng.uniform(-12, 12), ly + rng.uniform(-8, 8), 0.0).car(
            rng.choice(free), None, "parked"
        )
        cars.append(parked)

        order = list(range(len(cars)))
        rng.shuffle(order)
        for n, i in enumerate(order, start=1):
            cars[i].id = f"car{n}"
        self._cars = sorted(cars, key=lambda c: int(c.id[3:]))
        truth = []
        for ev in events:
            sx, sy = ev.car.xy(ev.start)
            ex, ey = ev.car.xy(ev.end)
            start_area, end_area = self.area_of(sx, sy), self.area_of(ex, ey)
            assert start_area is not None and end_area is not None
            truth.append(
                Violation(
                    ev.kind,
                    ev.car.id,
                    ev.other.id if ev.other is not None else None,
                    ev.start,
                    ev.end,
                    start_area,
                    end_area,
                    ex,
                    ey,
                )
            )
        self._truth = sorted(truth, key=lambda v: v.end)

    def _legal_overtake(self, rng: random.Random, limit: float, cruise: float) -> _Event | None:
        """A car at cruising speed (<= the limit) passes a slow one, all inside area 0."""
        slow = limit * rng.uniform(0.55, 0.65)
        dv = cruise - slow
        pull_in = rng.uniform(10.0, 15.0)
        span = (BESIDE_DISTANCE + pull_in) / dv + _LANE_CHANGE_S
        start = _pick_time(rng, 16.0, 36.0, self.duration - 10.5 - span)
        if start is None:
            return None
        margin = rng.uniform(2.0, 4.0)
        end_gap = pull_in + dv * _LANE_CHANGE_S
        lo = BESIDE_DISTANCE + 12 * cruise + 15.0  # the overtaker in area 0 12 s before
        hi = AREA_WIDTH - 20.0 - (slow * span + end_gap)
        if lo > hi:
            raise _Rejected
        xs = rng.uniform(lo, hi)  # the slow car at the start
        slow_car = _Path(start, xs, _DRIVE_Y, slow).car("", "r1", "slow")
        out_at = start - margin / dv - _LANE_CHANGE_S
        lateral = LANE_WIDTH / _LANE_CHANGE_S
        x_out = xs - BESIDE_DISTANCE + cruise * (out_at - start)
        path = _Path(out_at - 1.0, x_out - cruise, _DRIVE_Y, cruise).go(1.0, "r1", "normal")
        path.go(_LANE_CHANGE_S, "r1", "overtaking", vy=lateral)
        path.go(margin / dv + (BESIDE_DISTANCE + pull_in) / dv, "r1", "overtaking", vy=0.0)
        path.go(_LANE_CHANGE_S, "r1", "overtaking", vy=-lateral)
        path.vy = 0.0
        car = path.car("", "r1", "normal")
        return _Event("overtake", car, slow_car, start, start + span)

    def _reckless_overtake(self, rng: random.Random, limit: float, cruise: float) -> _Event | None:
        """The handover: a speeding car passes another across the last border.

        It swerves out late and fast (so the UAVs see it behind, within 40 m, first), passes
        at more than 1.3 x the limit, and brakes back to the traffic's speed while cutting
        in, so it ends 15-36 m ahead and stays in front for a while.
        """
        border = self.border(self.n_uavs - 2)
        fast = limit * rng.uniform(1.36, 1.5)
        dv = fast - cruise
        swerve = 1.5
        after = min(limit, cruise * rng.uniform(1.03, 1.08))
        # The pair must start 25 m before the border and end 25 m beyond it: the overtaken
        # car has to cover 50 m (plus slack) during the overtake.
        needed = (56.0 + rng.uniform(4.0, 16.0)) / cruise
        pull_in = max(rng.uniform(12.0, 18.0), (needed - _LANE_CHANGE_S) * dv - BESIDE_DISTANCE)
        end_gap = pull_in + _LANE_CHANGE_S * ((fast + after) / 2 - cruise)
        if end_gap > 36.0:
            raise _Rejected
        span = (BESIDE_DISTANCE + pull_in) / dv + _LANE_CHANGE_S
        start = _pick_time(rng, 24.0, 36.0, self.duration - 10.5 - span)
        if start is None:
            return None
        lo, hi = border + 28.0 - cruise * span, border - 28.0
        if lo > hi:
            raise _Rejected
        xh = rng.uniform(lo, hi)  # the overtaken car at the start
        other = _Path(start, xh, _DRIVE_Y, cruise).car("", "r1", "normal")
        margin = rng.uniform(2.0, 4.0)
        out_at = start - margin / dv - swerve
        x_out = xh - BESIDE_DISTANCE + fast * (out_at - start)
        path = _Path(out_at - 1.0, x_out - fast, _DRIVE_Y, fast).go(1.0, "r1", "normal")
        path.go(swerve, "r1", "reckless", vy=LANE_WIDTH / swerve)
        path.go(margin / dv + (BESIDE_DISTANCE + pull_in) / dv, "r1", "reckless", vy=0.0)
        path.go(
            _LANE_CHANGE_S,
            "r1",
            "reckless",
            vy=-LANE_WIDTH / _LANE_CHANGE_S,
            ax=(after - fast) / _LANE_CHANGE_S,
        )
        path.vy = 0.0
        car = path.car("", "r1", "normal")
        if path.x + after * 8.0 > border + AREA_WIDTH - 10.0:  # visible for 8 s after the end
            raise _Rejected
        return _Event("reckless-overtake", car, other, start, start + span)

    def _turn(self, rng: random.Random, cruise: float) -> _Event | None:
        """A car on r1 slows down and turns onto an area's north-south road."""
        crossing = rng.choice(self.crossings)
        side_road = crossing.roads[1]
        ns_speed = self._limits[side_road] * rng.uniform(0.8, 0.95)
        v_turn = rng.uniform(5.0, 7.0)
        brake = rng.uniform(25.0, 40.0)
        left = rng.random() < 0.5
        radius = 9.0 if left else 6.0
        if left:  # north, into the east lane of the side road
            lane_x = crossing.x + LANE_WIDTH / 2
            cx, cy, angle, omega = lane_x - radius, _DRIVE_Y + radius, -math.pi / 2, 1.0
        else:  # south, into its west lane
            lane_x = crossing.x - LANE_WIDTH / 2
            cx, cy, angle, omega = lane_x - radius, _DRIVE_Y - radius, math.pi / 2, -1.0
        omega *= v_turn / radius
        quarter = (math.pi / 2) / abs(omega)
        t_brake = 2 * brake / (cruise + v_turn)
        path = _Path(-1.0, cx - brake - cruise, _DRIVE_Y, cruise).go(1.0, "r1", "normal")
        path.go(t_brake, "r1", "turning", ax=(v_turn - cruise) / t_brake)
        half = quarter / 2  # the car belongs to the side road from half-way round
        path.arc((cx, cy), radius, angle, omega, half, "r1", "turning")
        path.arc((cx, cy), radius, angle + omega * half, omega, half, side_road, "turning")
        direction = 1.0 if left else -1.0
        path.go(3.0, side_road, "turning", vx=0.0, ay=direction * (ns_speed - v_turn) / 3.0)
        car = path.car("", side_road, "normal")
        enter, leave = _circle_crossings(car, crossing, -1.0, path.t)
        start = _pick_time(rng, 18.0, 32.0, self.duration - 10.5 - (leave - enter))
        if start is None:
            return None
        shifted = _shift(car, start - enter)
        # Found again on the shifted path, so both ends are exactly inside the circle.
        start, end = _circle_crossings(shifted, crossing, start - 1.0, start + leave - enter + 1.0)
        x_before, _ = shifted.xy(start - 12.0)
        if self.area_of(x_before, _DRIVE_Y) != self.crossings.index(crossing):
            raise _Rejected
        return _Event("turn", shifted, None, start, end)


def _road_network(rng: random.Random, n: int) -> tuple[tuple[Road, ...], tuple[Crossing, ...]]:
    """The main road and one north-south road per area, with their crossings."""
    width = AREA_WIDTH * n
    main_limit = round(rng.uniform(13.0, 16.0), 1)
    roads = [Road("r1", (0.0, MAIN_Y), (width, MAIN_Y), main_limit)]
    crossings = []
    for i in range(n):
        x = round(AREA_WIDTH * i + rng.uniform(220.0, 380.0), 1)
        rid = f"r{i + 2}"
        roads.append(Road(rid, (x, 0.0), (x, WORLD_HEIGHT), round(rng.uniform(9.0, 12.0), 1)))
        crossings.append(Crossing(f"c{i + 1}", x, MAIN_Y, CROSSING_RADIUS, ("r1", rid)))
    return tuple(roads), tuple(crossings)


def _shift(car: _Car, dt: float) -> _Car:
    """The same path, dt later."""
    return _Car([(leg[0] + dt, *leg[1:]) for leg in car.legs], car.colour)


def _circle_crossings(car: _Car, c: Crossing, t0: float, t1: float) -> tuple[float, float]:
    """When the car enters and leaves the crossing's circle, between t0 and t1."""

    def inside(t: float) -> bool:
        x, y = car.xy(t)
        return (x - c.x) ** 2 + (y - c.y) ** 2 <= c.radius * c.radius

    ts = [t0 + i * 0.05 for i in range(int((t1 - t0) / 0.05) + 1)]
    flags = [inside(t) for t in ts]
    enter = next(i for i in range(1, len(ts)) if flags[i] and not flags[i - 1])
    leave = next(i for i in range(enter, len(ts)) if not flags[i])
    return _bisect(inside, ts[enter - 1], ts[enter]), _bisect_last(inside, ts[leave - 1], ts[leave])


def _bisect(pred: Callable[[float], bool], a: float, b: float) -> float:
    """The first time in (a, b] where ``pred`` has changed value (pred(a) != pred(b))."""
    at_a = pred(a)
    for _ in range(40):
        mid = (a + b) / 2
        if pred(mid) == at_a:
            a = mid
        else:
            b = mid
    return b


def _pick_time(rng: random.Random, lo: float, hi: float, latest: float) -> float | None:
    """A start time in [lo, hi] clipped to [lead-in, latest]; None when nothing fits."""
    hi = min(hi, latest)
    lo = max(_LEAD_IN_S, min(lo, hi))
    if hi < lo:
        return None
    return rng.uniform(lo, hi)


def _track(car: _Car, grid: list[float]) -> list[tuple[float, float] | None]:
    """The car's on-road positions on the grid (None while gone or off-road)."""
    out: list[tuple[float, float] | None] = []
    for t in grid:
        if car.t_in <= t <= car.t_out:
            x, y, _, _, road, _ = car.state(t)
            out.append((x, y) if road is not None else None)
        else:
            out.append(None)
    return out


def _too_close(a: list[tuple[float, float] | None], b: list[tuple[float, float] | None]) -> bool:
    """Whether two tracks ever come within the clearance of each other."""
    limit = _CLEARANCE * _CLEARANCE
    for p, q in zip(a, b, strict=True):
        if p is not None and q is not None:
            dx, dy = p[0] - q[0], p[1] - q[1]
            if dx * dx + dy * dy < limit:
                return True
    return False


def _segment_distance(x: float, y: float, a: tuple[float, float], b: tuple[float, float]) -> float:
    """The distance from (x, y) to the segment a-b."""
    ax, ay = a
    dx, dy = b[0] - ax, b[1] - ay
    length2 = dx * dx + dy * dy
    u = 0.0 if length2 == 0 else max(0.0, min(1.0, ((x - ax) * dx + (y - ay) * dy) / length2))
    return math.hypot(x - (ax + u * dx), y - (ay + u * dy))


class Camera:
    """One UAV's camera over its area: noisy detections with camera-local track ids."""

    def __init__(
        self,
        world: World,
        area: int,
        *,
        seed: int | None = None,
        noise: float = 0.5,
        miss: float = 0.02,
    ) -> None:
        self.world = world
        self.area = world._area(area)
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise ValueError(f"seed must be an int or None, not {seed!r}")
        if not (isinstance(noise, int | float) and math.isfinite(noise) and noise >= 0):
            raise ValueError(f"noise must be a non-negative number of metres, not {noise!r}")
        if not (isinstance(miss, int | float) and 0 <= miss <= 1):
            raise ValueError(f"miss must be a probability in [0, 1], not {miss!r}")
        self.seed = world.seed if seed is None else seed
        self.noise = float(noise)
        self.miss = float(miss)
        self._key = (abs(self.seed) * 2 + (self.seed < 0)) * 64 + self.area.index
        # Each stay of a car in view is an episode with its own vid, numbered by start time,
        # so a vid depends on t alone and not on which times were observed before.
        found: list[tuple[float, int, float]] = []
        for i, car in enumerate(world._cars):
            for start, end in _episodes(car, self.area):
                found.append((start, i, end))
        found.sort()
        self._episodes: list[list[tuple[float, float, str]]] = [[] for _ in world._cars]
        for n, (start, i, end) in enumerate(found, start=1):
            self._episodes[i].append((start, end, f"v{n}"))

    def observe(self, t: float) -> list[VisionObject]:
        """The detections at t of the cars in view: gaussian noise, some missed, by vid."""
        rng = random.Random(self._key * 1_000_000_007 + round(t * 1000))
        out = []
        for car, episodes in zip(self.world._cars, self._episodes, strict=True):
            vid = next((v for start, end, v in episodes if start <= t <= end), None)
            if vid is None:
                continue
            if rng.random() < self.miss:
                continue
            x, y = car.xy(t)
            out.append(
                VisionObject(
                    vid, x + rng.gauss(0.0, self.noise), y + rng.gauss(0.0, self.noise), car.colour
                )
            )
        return out


def _episodes(car: _Car, area: Area) -> list[tuple[float, float]]:
    """The time intervals during which the car is inside the area."""
    if car.t_in == -math.inf or car.t_out == math.inf:
        x, y = car.xy(0.0)  # only parked cars live forever, and they stand still
        return [(-math.inf, math.inf)] if area.contains(x, y) else []

    def inside(t: float) -> bool:
        x, y = car.xy(t)
        return area.contains(x, y)

    step = 0.25
    n = max(1, math.ceil((car.t_out - car.t_in) / step))
    ts = [car.t_in + (car.t_out - car.t_in) * i / n for i in range(n + 1)]
    out = []
    start: float | None = None
    prev_t, prev_in = ts[0], inside(ts[0])
    if prev_in:
        start = ts[0]
    for t in ts[1:]:
        now = inside(t)
        if now != prev_in:
            edge = _bisect(inside, prev_t, t)
            if now:
                start = edge
            elif start is not None:
                out.append((start, _bisect_last(inside, prev_t, t)))
                start = None
        prev_t, prev_in = t, now
    if start is not None:
        out.append((start, ts[-1]))
    return out


def _bisect_last(pred: Callable[[float], bool], a: float, b: float) -> float:
    """The last time in [a, b) where ``pred`` still holds (pred(a) true, pred(b) false)."""
    for _ in range(40):
        mid = (a + b) / 2
        if pred(mid):
            a = mid
        else:
            b = mid
    return a
