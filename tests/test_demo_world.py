"""The traffic demo's simulated world: determinism, the scripted events, the camera, the GIS."""

from __future__ import annotations

import json
import math
import statistics
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from federation.demo._world import (
    BESIDE_DISTANCE,
    LANE_WIDTH,
    Camera,
    CarTruth,
    Violation,
    World,
    _Path,
)

DT = 0.1


def grid(a: float, b: float, dt: float = DT) -> list[float]:
    n = round((b - a) / dt)
    return [a + i * dt for i in range(n + 1)]


def by_id(world: World, t: float) -> dict[str, CarTruth]:
    return {c.id: c for c in world.cars_at(t)}


def scripted_pairs(world: World) -> set[frozenset[str]]:
    return {frozenset((v.car, v.other)) for v in world.ground_truth() if v.other is not None}


def check_world(world: World) -> None:
    """Every rule the scenario promises, checked from the public API only."""
    truth = world.ground_truth()
    limit = world.speed_limit("r1")
    assert [v.end for v in truth] == sorted(v.end for v in truth)
    for v in truth:
        assert 0 <= v.start < v.end < world.duration - 10
        check_lead_in(world, v)
        if v.kind == "overtake":
            check_overtake(world, v, limit)
            assert v.start_area == v.end_area == 0
        elif v.kind == "reckless-overtake":
            check_overtake(world, v, limit)
            check_handover(world, v, limit)
        else:
            assert v.kind == "turn"
            check_turn(world, v)
    check_no_accidents(world)


def check_lead_in(world: World, v: Violation) -> None:
    """Every car of an event is on a road inside the start area for 12 s before it starts."""
    for name in (v.car, v.other):
        if name is None:
            continue
        for t in grid(v.start - 12.0, v.start):
            car = by_id(world, t).get(name)
            assert car is not None, (name, t)
            assert car.road is not None, (name, t)
            assert world.area_of(car.x, car.y) == v.start_area, (name, t)


def check_overtake(world: World, v: Violation, limit: float) -> None:
    """Behind, then beside in the other lane, then back in the lane ahead."""
    assert v.other is not None
    before = by_id(world, v.start - 3.0)
    assert before[v.car].x < before[v.other].x - BESIDE_DISTANCE
    at = by_id(world, v.start)
    assert abs(at[v.car].x - at[v.other].x) == pytest.approx(BESIDE_DISTANCE, abs=0.05)
    assert abs(at[v.car].y - at[v.other].y) == pytest.approx(LANE_WIDTH, abs=0.05)
    # The UAVs see it behind, in the same lane within 40 m, for a while before...
    behind = [
        t
        for t in grid(v.start - 8.0, v.start)
        if abs(by_id(world, t)[v.car].y - by_id(world, t)[v.other].y) < 1.5
        and -40.0 < by_id(world, t)[v.car].x - by_id(world, t)[v.other].x < -6.0
    ]
    assert len(behind) * DT >= 1.0
    # ...and in front, back in the lane and still within 40 m, at the end.
    end = by_id(world, v.end)
    assert 10.0 <= end[v.car].x - end[v.other].x <= 36.5
    assert end[v.car].y == pytest.approx(end[v.other].y, abs=0.05)
    assert (v.x, v.y) == pytest.approx((end[v.car].x, end[v.car].y))
    beside_speeds = []
    for t in grid(v.start, v.end):
        cars = by_id(world, t)
        me, other = cars[v.car], cars[v.other]
        if abs(me.x - other.x) < BESIDE_DISTANCE:
            assert abs(me.y - other.y) > 3.0  # never bumps into it
            beside_speeds.append(me.speed)
    assert beside_speeds
    if v.kind == "overtake":
        assert max(beside_speeds) <= limit
        assert by_id(world, v.start)[v.other].behaviour == "slow"
    else:
        assert min(beside_speeds) > 1.3 * limit


def check_handover(world: World, v: Violation, limit: float) -> None:
    """The reckless overtake crosses the last border with 25 m margins, both cars then stay."""
    assert v.other is not None
    k = world.n_uavs - 2
    border = world.border(k)
    assert (v.start_area, v.end_area) == (k, k + 1)
    start, end = by_id(world, v.start), by_id(world, v.end)
    for name in (v.car, v.other):
        assert start[name].x <= border - 25.0
        assert end[name].x >= border + 25.0
        for t in grid(v.end, v.end + 8.0):
            car = by_id(world, t)[name]
            assert world.area_of(car.x, car.y) == k + 1
    colours = [c.colour for c in world.cars_at(v.start)]
    assert colours.count(start[v.car].colour) == 1
    assert colours.count(start[v.other].colour) == 1


def check_turn(world: World, v: Violation) -> None:
    """From the main road through a crossing onto that crossing's north-south road."""
    at_start, at_end = by_id(world, v.start)[v.car], by_id(world, v.end)[v.car]
    crossing = world.crossing_at(at_start.x, at_start.y)
    assert crossing is not None
    assert world.crossing_at(at_end.x, at_end.y) == crossing
    assert by_id(world, v.start - 0.2)[v.car].road == "r1"
    assert world.crossing_at(*xy(by_id(world, v.start - 0.2)[v.car])) is None
    after = by_id(world, v.end + 0.2)[v.car]
    assert world.crossing_at(after.x, after.y) is None
    side = next(c for c in world.crossings if c.id == crossing).roads[1]
    assert after.road == side == world.road_at(after.x, after.y)
    assert v.start_area == v.end_area == world.area_of(at_start.x, at_start.y)


def xy(car: CarTruth) -> tuple[float, float]:
    return car.x, car.y


def check_no_accidents(world: World) -> None:
    """Outside the scripted pairs no two on-road cars come within 40 m; only turners turn."""
    pairs = scripted_pairs(world)
    turners = {v.car for v in world.ground_truth() if v.kind == "turn"}
    roads: dict[str, list[str]] = {}
    for t in grid(0.0, world.duration):
        cars = [c for c in world.cars_at(t) if c.road is not None]
        for c in cars:
            seq = roads.setdefault(c.id, [c.road])  # type: ignore[list-item]
            if seq[-1] != c.road:
                seq.append(c.road)  # type: ignore[arg-type]
        for i, a in enumerate(cars):
            for b in cars[i + 1 :]:
                if frozenset((a.id, b.id)) not in pairs:
                    assert math.hypot(a.x - b.x, a.y - b.y) >= 40.0, (t, a, b)
    for name, seq in roads.items():
        assert len(seq) == 1 or (name in turners and len(seq) == 2), (name, seq)


# --- the scenario -------------------------------------------------------------------------


@pytest.mark.parametrize("n_uavs", [2, 3, 4])
def test_the_scripted_events_happen_as_promised(n_uavs: int) -> None:
    world = World.generate(7, n_uavs=n_uavs)
    kinds = sorted(v.kind for v in world.ground_truth())
    assert kinds == ["overtake", "reckless-overtake", "turn"]
    check_world(world)


def test_one_uav_has_no_handover_but_the_other_events() -> None:
    world = World.generate(3, n_uavs=1)
    assert sorted(v.kind for v in world.ground_truth()) == ["overtake", "turn"]
    check_world(world)


@settings(max_examples=12)
@given(
    seed=st.integers(0, 2**31),
    n_uavs=st.integers(1, 6),
    duration=st.sampled_from([30.0, 45.0, 60.0, 75.0]),
)
def test_any_seed_size_and_duration_keeps_the_rules(
    seed: int, n_uavs: int, duration: float
) -> None:
    world = World.generate(seed, n_uavs=n_uavs, duration=duration)
    kinds = sorted(v.kind for v in world.ground_truth())
    if duration >= 60:
        expected = (
            ["overtake", "reckless-overtake", "turn"] if n_uavs >= 2 else ["overtake", "turn"]
        )
        assert kinds == expected
    check_world(world)
    involved = {name for v in world.ground_truth() for name in (v.car, v.other)}
    others = {
        c.id
        for t in grid(0.0, world.duration, 1.0)
        for c in world.cars_at(t)
        if c.id not in involved and c.behaviour != "parked"
    }
    assert 3 <= len(others) <= 6


def test_a_world_too_short_for_events_has_only_traffic() -> None:
    world = World.generate(5, n_uavs=3, duration=20.0)
    assert world.ground_truth() == []
    assert world.cars_at(0.0)
    check_no_accidents(world)


def test_the_map_has_a_main_road_and_a_crossing_per_area() -> None:
    world = World.generate(11, n_uavs=4)
    assert (world.width, world.height) == (2400.0, 400.0)
    assert [a.index for a in world.areas] == [0, 1, 2, 3]
    assert world.areas[0].x0 == 0 and world.areas[-1].x1 == world.width
    assert world.roads[0].id == "r1" and world.roads[0].lanes == 2
    for area, crossing in zip(world.areas, world.crossings, strict=True):
        assert area.contains(crossing.x, crossing.y)
        assert crossing.roads[0] == "r1"


# --- determinism --------------------------------------------------------------------------


def test_the_same_seed_gives_the_same_world_and_another_seed_another() -> None:
    a, b, c = World.generate(42), World.generate(42), World.generate(43)
    for t in (0.0, 13.37, 30.0, 59.9):
        assert a.cars_at(t) == b.cars_at(t)
    assert a.ground_truth() == b.ground_truth()
    assert a.to_dict() == b.to_dict()
    assert Camera(a, 1).observe(21.5) == Camera(b, 1).observe(21.5)
    assert a.ground_truth() != c.ground_truth()
    assert a.to_dict() != c.to_dict()


def test_cars_at_is_a_pure_function_of_time() -> None:
    world = World.generate(8)
    times = [0.0, 50.0, 12.5, 33.3, 0.0, 12.5]
    first = [world.cars_at(t) for t in times]
    again = [world.cars_at(t) for t in reversed(times)][::-1]
    assert first == again
    assert first[0] == first[4]


# --- the camera ---------------------------------------------------------------------------


def match(world: World, t: float, detections: list, tol: float) -> dict[str, str]:
    """vid -> car id, by nearest true position."""
    cars = world.cars_at(t)
    out = {}
    for d in detections:
        best = min(cars, key=lambda c: math.hypot(c.x - d.x, c.y - d.y))
        assert math.hypot(best.x - d.x, best.y - d.y) < tol
        assert best.colour == d.colour
        out[d.vid] = best.id
    return out


def test_the_camera_sees_exactly_the_cars_in_its_area() -> None:
    world = World.generate(21, n_uavs=3)
    for index in range(3):
        camera = Camera(world, index, noise=0.0, miss=0.0)
        area = world.areas[index]
        for t in grid(0.0, 60.0, 0.5):
            seen = sorted((round(d.x, 6), round(d.y, 6)) for d in camera.observe(t))
            inside = sorted(
                (round(c.x, 6), round(c.y, 6)) for c in world.cars_at(t) if area.contains(c.x, c.y)
            )
            assert seen == inside


def test_the_camera_noise_and_misses_have_the_requested_statistics() -> None:
    world = World.generate(4, n_uavs=2)
    camera = Camera(world, 0, noise=0.5, miss=0.2)
    truth = Camera(world, 0, noise=0.0, miss=0.0)
    errors, seen, total = [], 0, 0
    for t in grid(0.0, 60.0, 0.05):
        exact = {d.vid: d for d in truth.observe(t)}
        noisy = camera.observe(t)
        total += len(exact)
        seen += len(noisy)
        for d in noisy:
            errors += [d.x - exact[d.vid].x, d.y - exact[d.vid].y]
    assert total > 2000
    assert seen / total == pytest.approx(0.8, abs=0.03)
    assert statistics.fmean(errors) == pytest.approx(0.0, abs=0.03)
    assert statistics.pstdev(errors) == pytest.approx(0.5, abs=0.03)


def test_vids_are_stable_while_in_view_and_never_shared() -> None:
    world = World.generate(9, n_uavs=3)
    camera = Camera(world, 1)
    vid_to_car: dict[str, str] = {}
    car_to_vids: dict[str, set[str]] = {}
    for t in grid(0.0, 60.0, 0.2):
        for vid, car in match(world, t, camera.observe(t), tol=4.0).items():
            assert vid_to_car.setdefault(vid, car) == car
            car_to_vids.setdefault(car, set()).add(vid)
    assert len(vid_to_car) >= 3
    # No car leaves area 1 and comes back in this world: one vid per car.
    assert all(len(v) == 1 for v in car_to_vids.values())


def test_a_car_that_comes_back_into_view_gets_a_fresh_vid() -> None:
    world = World.generate(9, n_uavs=2)
    # A car that drives east out of area 0, turns round in area 1 and drives back.
    path = _Path(0.0, 500.0, 150.0, 10.0).go(20.0, "r1", "normal")
    path.go(20.0, "r1", "normal", vx=-10.0)
    car = path.car("pink", "r1", "normal")
    car.id = "car99"
    car.clip_to(world.width, world.height)
    world._cars.append(car)
    camera = Camera(world, 0, noise=0.0, miss=0.0)

    def vid_at(t: float) -> str | None:
        return next((d.vid for d in camera.observe(t) if d.colour == "pink"), None)

    first, gone, back = vid_at(5.0), vid_at(20.0), vid_at(35.0)
    assert first is not None and back is not None and gone is None
    assert first != back
    assert vid_at(7.0) == first and vid_at(38.0) == back
    # A vid depends on the time only, not on what was observed before.
    assert Camera(world, 0, noise=0.0, miss=0.0).observe(38.0) == camera.observe(38.0)


def test_observe_does_not_depend_on_the_order_of_calls() -> None:
    world = World.generate(13)
    times = grid(10.0, 40.0, 1.0)
    forward = [Camera(world, 2).observe(t) for t in times]
    camera = Camera(world, 2)
    backward = [camera.observe(t) for t in reversed(times)][::-1]
    assert forward == backward
    assert Camera(world, 2, seed=1).observe(25.0) != Camera(world, 2, seed=2).observe(25.0)


def test_the_parked_car_is_seen_but_is_off_road() -> None:
    world = World.generate(17, n_uavs=3)
    parked = [c for c in world.cars_at(30.0) if c.behaviour == "parked"]
    assert len(parked) == 1
    car = parked[0]
    assert car.road is None and car.speed == 0
    assert world.road_at(car.x, car.y) is None
    assert car == next(c for c in world.cars_at(0.0) if c.id == car.id)


# --- GIS, areas, UAVs, the map --------------------------------------------------------


def test_the_gis_answers_which_road_crossing_and_area() -> None:
    world = World.generate(1, n_uavs=3)
    side = world.roads[1]
    assert world.road_at(100.0, 201.0) == "r1"
    assert world.road_at(100.0, 194.5) == "r1"
    assert world.road_at(100.0, 190.0) is None
    assert world.road_at(100.0, 190.0, tolerance=12.0) == "r1"
    assert world.road_at(side.a[0] + 2.0, 50.0) == side.id
    crossing = world.crossings[0]
    assert world.crossing_at(crossing.x + 5.0, crossing.y - 5.0) == crossing.id
    assert world.crossing_at(crossing.x + 20.0, crossing.y) is None
    assert [world.area_of(x, 100.0) for x in (0.0, 599.0, 601.0, 1799.0)] == [0, 0, 1, 2]
    assert world.area_of(-1.0, 100.0) is None and world.area_of(10.0, 401.0) is None
    assert world.speed_limit("r1") == world.roads[0].speed_limit > 10.0
    with pytest.raises(ValueError, match="r99"):
        world.speed_limit("r99")


def test_uavs_hover_over_their_areas() -> None:
    world = World.generate(2, n_uavs=4)
    for area in world.areas:
        positions = [world.uav_position(area.index, t) for t in grid(0.0, 60.0, 1.0)]
        assert all(area.contains(x, y) and z > 0 for x, y, z in positions)
        assert len(set(positions)) > 1
    with pytest.raises(ValueError, match="area index"):
        world.uav_position(4, 0.0)


def test_the_map_is_json_ready() -> None:
    world = World.generate(6, n_uavs=2)
    data = json.loads(json.dumps(world.to_dict()))
    assert data["width"] == 1200.0 and data["height"] == 400.0
    assert [r["id"] for r in data["roads"]] == ["r1", "r2", "r3"]
    assert set(data["roads"][0]) == {"id", "a", "b", "speed_limit", "lanes"}
    assert data["areas"][1] == {
        "index": 1,
        "polygon": [[600.0, 0.0], [1200.0, 0.0], [1200.0, 400.0], [600.0, 400.0]],
    }
    assert [c["id"] for c in data["crossings"]] == ["c1", "c2"]


# --- bad input and speed ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"n_uavs": 0}, "n_uavs"),
        ({"n_uavs": -2}, "n_uavs"),
        ({"n_uavs": 2.5}, "n_uavs"),
        ({"duration": 0.0}, "duration"),
        ({"duration": -5.0}, "duration"),
        ({"duration": math.nan}, "duration"),
        ({"duration": "60"}, "duration"),
        ({"seed": "x"}, "seed"),
    ],
)
def test_bad_arguments_are_refused_by_name(kwargs: dict, name: str) -> None:
    args = {"seed": 1, **kwargs}
    with pytest.raises(ValueError, match=name):
        World.generate(**args)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [({"area": 3}, "area"), ({"noise": -0.1}, "noise"), ({"miss": 1.5}, "miss")],
)
def test_bad_camera_arguments_are_refused_by_name(kwargs: dict, name: str) -> None:
    world = World.generate(1, n_uavs=3)
    args = {"area": 0, **kwargs}
    area = args.pop("area")
    with pytest.raises(ValueError, match=name):
        Camera(world, area, **args)


def test_queries_are_fast_enough_for_10_hz_per_uav() -> None:
    world = World.generate(3, n_uavs=8)
    camera = Camera(world, 6)
    times = grid(0.0, 60.0, 0.1)
    began = time.perf_counter()
    for t in times:
        world.cars_at(t)
        camera.observe(t)
    per_call = (time.perf_counter() - began) / len(times)
    assert per_call < 500e-6  # measured ~30 µs for both; generous for loaded CI machines
