"""Chronicles: definitions checked for consistency, online recognition, as a process."""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dyknow_core._exceptions import UnknownLabelError
from dyknow_core._instance import DyKnowInstance
from dyknow_core._time import NS_PER_S, ManualClock
from dyknow_core.reasoning.chronicles import (
    ChronicleError,
    ChronicleProcess,
    ChronicleRecognizer,
    ChronicleSpec,
    Recognition,
    add_chronicle,
    compile_chronicle,
    recognize_all,
)

S = NS_PER_S

PASSED: dict[str, Any] = {
    "name": "passed",
    "events": [
        {"name": "enter", "event": "incross", "args": ["car"], "from": False, "to": True},
        {"name": "leave", "event": "incross", "args": ["car"], "from": True, "to": False},
    ],
    "constraints": [{"start": "enter", "end": "leave", "lo": 0, "hi": 20}],
}


def cross(car: str, old: bool, new: bool, t: float) -> tuple[str, int, dict[str, str], Any, Any]:
    return ("incross", round(t * S), {"car": car}, old, new)


def keyed(recs: list[Recognition]) -> list[tuple[Any, ...]]:
    return sorted((tuple(sorted(r.bindings.items())), tuple(sorted(r.times.items()))) for r in recs)


# -- definitions ------------------------------------------------------------------------------


def test_a_consistent_network_is_minimized() -> None:
    c = compile_chronicle(
        {
            "name": "abc",
            "events": [
                {"name": "a", "event": "x"},
                {"name": "b", "event": "y"},
                {"name": "c", "event": "z"},
            ],
            "constraints": [
                {"start": "a", "end": "b", "lo": 4, "hi": 10},
                {"start": "b", "end": "c", "lo": 3, "hi": 13},
                {"start": "a", "end": "c", "lo": 2, "hi": 8},
            ],
        }
    )
    assert c.window("a", "c") == (7.0, 8.0)
    assert c.window("a", "b") == (4.0, 5.0)
    assert c.window("c", "a") == (-8.0, -7.0)


def test_an_inconsistent_network_names_the_cycle() -> None:
    with pytest.raises(ChronicleError) as info:
        compile_chronicle(
            {
                "name": "bad",
                "events": [
                    {"name": "a", "event": "x"},
                    {"name": "b", "event": "x"},
                    {"name": "c", "event": "x"},
                    {"name": "d", "event": "x"},
                ],
                "constraints": [
                    {"start": "a", "end": "b", "lo": 5, "hi": 10},
                    {"start": "b", "end": "c", "lo": 5, "hi": 10},
                    {"start": "a", "end": "c", "lo": 0, "hi": 8},
                    {"start": "c", "end": "d", "lo": 0, "hi": 1},
                ],
            }
        )
    msg = str(info.value)
    assert info.value.field == "constraints"
    assert "negative cycle" in msg
    assert "a -> b [5.0, 10.0]" in msg
    assert "b -> c [5.0, 10.0]" in msg
    assert "a -> c [0.0, 8.0]" in msg
    assert "c -> d" not in msg


@pytest.mark.parametrize(
    ("definition", "field"),
    [
        ({"name": "x", "events": []}, "events"),
        ({"name": "x", "events": [{"name": "a", "event": "e", "oops": 1}]}, "events.0.oops"),
        (
            {"name": "x", "events": [{"name": "a", "event": "e"}, {"name": "a", "event": "e"}]},
            "events.1.name",
        ),
        (
            {
                "name": "x",
                "events": [{"name": "a", "event": "e"}],
                "constraints": [{"start": "a", "end": "zz", "hi": 1}],
            },
            "constraints.0.end",
        ),
        (
            {
                "name": "x",
                "events": [{"name": "a", "event": "e"}, {"name": "b", "event": "e"}],
                "constraints": [{"start": "a", "end": "b", "lo": 3, "hi": 1}],
            },
            "constraints.0",
        ),
        (
            {
                "name": "x",
                "events": [{"name": "a", "event": "e"}, {"name": "b", "event": "e", "args": ["c"]}],
                "forbidden": [{"event": "f", "args": ["c"], "start": "a", "hi": 1}],
            },
            "forbidden.0.args",
        ),
        (
            {
                "name": "x",
                "events": [{"name": "a", "event": "e"}],
                "forbidden": [{"event": "f", "start": "a"}],
            },
            "forbidden.0.hi",
        ),
        ({"name": "x", "events": [{"name": "a", "event": "e"}], "max_partial": 0}, "max_partial"),
    ],
)
def test_invalid_definitions_name_the_field(definition: dict[str, Any], field: str) -> None:
    with pytest.raises(ChronicleError) as info:
        compile_chronicle(definition)
    assert info.value.field == field


# -- recognition --------------------------------------------------------------------------


def test_passed_an_intersection_per_car() -> None:
    events = [
        cross("car1", False, True, 0),
        cross("car2", False, True, 1),
        cross("car2", True, False, 4),
        cross("car1", True, False, 12),
        cross("car3", False, True, 13),
        cross("car3", True, False, 40),  # 27 s: too late
    ]
    recs = recognize_all(PASSED, events)
    assert keyed(recs) == [
        ((("car", "car1"),), (("enter", 0), ("leave", 12 * S))),
        ((("car", "car2"),), (("enter", 1 * S), ("leave", 4 * S))),
    ]


def test_recognitions_come_as_soon_as_the_last_event_arrives() -> None:
    r = ChronicleRecognizer(PASSED)
    assert r.feed(*cross("car1", False, True, 0)) == []
    [rec] = r.feed(*cross("car1", True, False, 3))
    assert rec == Recognition("passed", {"car": "car1"}, {"enter": 0, "leave": 3 * S})


def test_overtake_binds_two_cars_in_order() -> None:
    # behind(a, b), then beside(a, b), then ahead(a, b) — each step within [0, 10] s
    spec = {
        "name": "overtake",
        "events": [
            {"name": "behind", "event": "rel", "args": ["a", "b"], "to": "behind"},
            {"name": "beside", "event": "rel", "args": ["a", "b"], "to": "beside"},
            {"name": "ahead", "event": "rel", "args": ["a", "b"], "to": "ahead"},
        ],
        "constraints": [
            {"start": "behind", "end": "beside", "lo": 0.1, "hi": 10},
            {"start": "beside", "end": "ahead", "lo": 0.1, "hi": 10},
            {"start": "behind", "end": "ahead", "hi": 15},
        ],
    }

    def rel(a: str, b: str, what: str, t: float) -> tuple[str, int, dict[str, str], Any, Any]:
        return ("rel", round(t * S), {"a": a, "b": b}, None, what)

    events = [
        rel("c1", "c2", "behind", 0),
        rel("c3", "c2", "behind", 1),
        rel("c1", "c2", "beside", 4),
        rel("c3", "c4", "beside", 5),  # another pair: does not advance c3/c2
        rel("c1", "c2", "ahead", 9),
        rel("c3", "c2", "beside", 9),
        rel("c3", "c2", "ahead", 17),  # 16 s after behind: too late
    ]
    recs = recognize_all(spec, events)
    assert keyed(recs) == [
        (
            (("a", "c1"), ("b", "c2")),
            (("ahead", 9 * S), ("behind", 0), ("beside", 4 * S)),
        )
    ]


def test_expired_partial_instances_are_freed() -> None:
    r = ChronicleRecognizer(PASSED)
    for k in range(50):
        r.feed(*cross(f"car{k}", False, True, k * 0.01))
    assert r.partial_instances() == 50
    assert r.feed(*cross("car0", True, False, 30)) == []  # too late
    assert r.stats().expired == 50
    # only the new "leave" waiting for an "enter" at the same instant is left
    assert r.partial_instances() == 1
    assert r.advance(31 * S) == []
    assert r.partial_instances() == 0


def test_forbidden_between_two_events_kills() -> None:
    # passed, but the car must not re-enter in between (no incross change in between)
    spec = dict(PASSED)
    spec["forbidden"] = [{"event": "incross", "args": ["car"], "start": "enter", "end": "leave"}]
    events = [
        cross("car1", False, True, 0),
        cross("car1", True, False, 5),
        cross("car1", False, True, 6),
        cross("car1", True, False, 8),
    ]
    # without the forbidden event: (0, 5), (0, 8), (6, 8); with it: the last change
    # between the events each time
    assert len(recognize_all(PASSED, events)) == 3
    recs = recognize_all(spec, events)
    assert keyed(recs) == [
        ((("car", "car1"),), (("enter", 0), ("leave", 5 * S))),
        ((("car", "car1"),), (("enter", 6 * S), ("leave", 8 * S))),
    ]


def test_forbidden_after_an_event_holds_the_recognition_until_the_window_closes() -> None:
    spec = dict(PASSED)
    # no alarm within 10 s after entering
    spec["forbidden"] = [{"event": "alarm", "start": "enter", "lo": 0, "hi": 10}]
    r = ChronicleRecognizer(spec)
    r.feed(*cross("car1", False, True, 0))
    assert r.feed(*cross("car1", True, False, 2)) == []  # the window is still open
    r.feed(*cross("car2", False, True, 3))
    assert r.feed(*cross("car2", True, False, 4)) == []
    assert r.feed("alarm", 11 * S) == [
        Recognition("passed", {"car": "car1"}, {"enter": 0, "leave": 2 * S})
    ]  # car1's window closed at 10 s; car2's alarm at 11 s killed it
    assert r.stats().killed == 2  # car2's held recognition and its waiting "enter"
    assert r.advance(100 * S) == []


def test_a_held_recognition_is_released_when_the_clock_reaches_the_window_end() -> None:
    """Held until the recognizer's clock (the newest input valid time, or advance/flush)
    reaches t(start) + hi; an event exactly at that time is outside the open window."""
    spec = dict(PASSED)
    spec["forbidden"] = [{"event": "alarm", "start": "enter", "lo": 0, "hi": 10}]
    r = ChronicleRecognizer(spec)
    r.feed(*cross("car1", False, True, 0))
    assert r.feed(*cross("car1", True, False, 2)) == []
    assert r.feed(*cross("car7", True, False, 2)) == []  # the clock did not move
    assert r.advance(10 * S - 1) == []
    recognized = Recognition("passed", {"car": "car1"}, {"enter": 0, "leave": 2 * S})
    assert r.feed("alarm", 10 * S) == [recognized]  # at 10 s: released, not killed
    assert r.stats().killed == 0
    # the same through advance (what ChronicleProcess.flush calls)
    r = ChronicleRecognizer(spec)
    r.feed(*cross("car1", False, True, 0))
    r.feed(*cross("car1", True, False, 2))
    assert r.advance(10 * S) == [recognized]


def test_forbidden_parameters_are_bound_by_the_start_event_or_free() -> None:
    spec = dict(PASSED)
    spec["forbidden"] = [
        # car is bound by "enter": only an alarm about that car kills
        {"event": "alarm", "args": ["car"], "start": "enter", "lo": 0, "hi": 10},
        # zone appears in no event: free, a siren about any zone kills
        {"event": "siren", "args": ["zone"], "start": "enter", "lo": 0, "hi": 10},
    ]
    recognized = Recognition("passed", {"car": "car1"}, {"enter": 0, "leave": 2 * S})

    def run(*forbidden: tuple[str, int, dict[str, str]]) -> list[Recognition]:
        r = ChronicleRecognizer(spec)
        r.feed(*cross("car1", False, True, 0))
        r.feed(*cross("car1", True, False, 2))
        for kind, t, args in forbidden:
            assert r.feed(kind, t, args) == []
        return r.advance(20 * S)

    # another car's alarm, or one that does not say which car, kills nothing
    assert run(("alarm", 3 * S, {"car": "car2"}), ("alarm", 4 * S, {})) == [recognized]
    assert run(("alarm", 3 * S, {"car": "car1"})) == []
    assert run(("siren", 3 * S, {"zone": "z9"})) == []
    assert run(("siren", 3 * S, {})) == []
    # a parameter bound only by another event than the start one is refused
    bad = dict(PASSED)
    bad["events"] = [
        {"name": "enter", "event": "incross", "from": False, "to": True},
        {"name": "leave", "event": "incross", "args": ["car"], "from": True, "to": False},
    ]
    bad["forbidden"] = [{"event": "alarm", "args": ["car"], "start": "enter", "end": "leave"}]
    with pytest.raises(ChronicleError, match="must be bound by the start event 'enter'"):
        compile_chronicle(bad)


def test_chronicle_over_a_chronicle() -> None:
    passed = compile_chronicle(PASSED)
    twice = {
        "name": "twice",
        "events": [
            {"name": "first", "event": "passed", "args": ["car"]},
            {"name": "second", "event": "passed", "args": ["car"]},
        ],
        "constraints": [{"start": "first", "end": "second", "lo": 0.001, "hi": 60}],
    }
    inner = ChronicleRecognizer(passed)
    outer = ChronicleRecognizer(twice)
    found: list[Recognition] = []
    for kind, t, args, old, new in [
        cross("car1", False, True, 0),
        cross("car1", True, False, 5),
        cross("car2", False, True, 6),
        cross("car2", True, False, 7),
        cross("car1", False, True, 30),
        cross("car1", True, False, 35),
    ]:
        for rec in inner.feed(kind, t, args, old, new):
            found += outer.feed("passed", max(rec.times.values()), rec.bindings, None, rec)
    # car1 passed at 5 s and at 35 s (and the 0→35 pair is an occurrence of "passed" too)
    assert {(r.bindings["car"], r.times["first"], r.times["second"]) for r in found} == {
        ("car1", 5 * S, 35 * S)
    }


def test_partial_instances_are_capped_under_a_long_stream() -> None:
    spec = dict(PASSED)
    spec["max_partial"] = 1000
    spec["constraints"] = [{"start": "enter", "end": "leave", "lo": 0}]  # never expires
    r = ChronicleRecognizer(spec)
    for k in range(100_000):
        r.feed("incross", k * 1000, {"car": f"car{k}"}, False, True)
    st_ = r.stats()
    assert st_.partial == 1000
    assert st_.dropped == 99_000
    assert len(r._expiry) <= 2 * 1000 + 64
    assert sum(len(b) for sub in r._index[1].values() for b in sub.values()) == 1000


# -- as a process on an instance ------------------------------------------------------------


def test_add_chronicle_publishes_recognitions_and_chains() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    srcs = {c: inst.add_source(f"car/{c}/incross") for c in ("car1", "car2")}
    for c in srcs:
        inst.add_change_events(f"car/{c}/incross", "any_change")
    proc = add_chronicle(inst, PASSED, {"incross": "events/changed/car/{car}/incross"})
    assert isinstance(proc, ChronicleProcess)
    assert proc.label == "chronicles/passed"
    twice = add_chronicle(
        inst,
        {
            "name": "twice",
            "events": [
                {"name": "first", "event": "passed", "args": ["car"]},
                {"name": "second", "event": "passed", "args": ["car"]},
            ],
            "constraints": [{"start": "first", "end": "second", "lo": 0.001, "hi": 60}],
        },
        {"passed": "chronicles/passed"},
    )
    # a verdict-like boolean feature per car, in time order
    for t, car, v in [
        (0, "car1", False),
        (0, "car2", False),
        (1, "car1", True),
        (3, "car1", False),
        (4, "car2", True),
        (30, "car2", False),  # 26 s: not passed
        (40, "car1", True),
        (45, "car1", False),
    ]:
        srcs[car].push(v, t * S, t * S + 1)
    got = [s[0] for s in inst.stream("chronicles/passed").cache.samples()]
    assert [(r.bindings["car"], r.times["enter"] // S, r.times["leave"] // S) for r in got] == [
        ("car1", 1, 3),
        ("car1", 40, 45),
    ]
    again = [s[0] for s in inst.stream("chronicles/twice").cache.samples()]
    assert [(r.bindings, r.times["first"] // S, r.times["second"] // S) for r in again] == [
        ({"car": "car1"}, 3, 45)
    ]
    assert proc.describe()["recognized"] == 2
    inst.remove_process(twice.name)
    assert not inst.has_label("chronicles/twice")


def test_add_chronicle_needs_a_label_for_every_event() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    with pytest.raises(ChronicleError) as info:
        add_chronicle(inst, PASSED, {})
    assert info.value.field == "inputs"

    with pytest.raises(ChronicleError, match=r"event\(s\) incross \(no event reads 'incros'\)"):
        add_chronicle(inst, PASSED, {"incros": "events/changed/car/{car}/incross"})


def test_add_chronicle_refuses_an_unknown_input_label_before_publishing() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    inst.add_source("events/changed/car/car5/incross")
    with pytest.raises(UnknownLabelError, match="'events/changed/car/car5/incros'") as info:
        add_chronicle(inst, PASSED, {"incross": "events/changed/car/car5/incros"})
    assert "chronicles/passed" not in str(info.value)  # not its own output, made and removed
    assert inst.labels() == ["events/changed/car/car5/incross"]


def test_mapping_values_carry_the_arguments() -> None:
    inst = DyKnowInstance(clock=ManualClock())
    src = inst.add_source("crossings")
    add_chronicle(inst, ChronicleSpec.model_validate(PASSED), {"incross": "crossings"})
    src.push({"car": "c9", "old": False, "new": True}, 0, 1)
    src.push({"car": "c9", "old": True, "new": False}, 2 * S, 2 * S + 1)
    [(rec, tv, _)] = list(inst.stream("chronicles/passed").cache.samples())
    assert rec.bindings == {"car": "c9"} and tv == 2 * S


# -- against a brute-force batch matcher --------------------------------------------------

Event = tuple[str, int, Mapping[str, Any], Any, Any]


def brute_force(spec: dict[str, Any], events: list[Event]) -> list[tuple[Any, ...]]:
    """Every injective assignment of events to the chronicle's events that satisfies it."""
    c = compile_chronicle(spec)
    out = []
    for combo in itertools.permutations(range(len(events)), len(c.nodes)):
        binds: dict[str, Any] = {}
        ok = True
        for nd, k in zip(c.nodes, combo, strict=True):
            kind, _t, args, old, new = events[k]
            if kind != nd.kind or (nd.has_from and old != nd.from_) or (nd.has_to and new != nd.to):
                ok = False
                break
            for arg, p in nd.params:
                if arg not in args or binds.setdefault(c.params[p], args[arg]) != args[arg]:
                    ok = False
                    break
            if not ok:
                break
        if not ok:
            continue
        times = [events[k][1] for k in combo]
        for con in c.spec.constraints:
            a = next(n.pos for n in c.nodes if n.name == con.start)
            b = next(n.pos for n in c.nodes if n.name == con.end)
            d = times[b] - times[a]
            if (con.lo is not None and d < round(con.lo * S)) or (
                con.hi is not None and d > round(con.hi * S)
            ):
                ok = False
        for f in c.forbids:
            ta = times[f.start]
            lo, hi = (ta, times[f.end]) if f.end >= 0 else (ta + f.lo, ta + f.hi)
            for kind, t, args, old, new in events:
                if kind != f.kind or not lo < t < hi:
                    continue
                if (f.has_from and old != f.from_) or (f.has_to and new != f.to):
                    continue
                if all(args.get(a) == binds[c.params[p]] for a, p in f.params):
                    ok = False
        if ok:
            out.append(
                (
                    tuple(sorted(binds.items())),
                    tuple(sorted(zip([n.name for n in c.nodes], times, strict=True))),
                )
            )
    return sorted(out)


bounds = st.one_of(st.none(), st.integers(-3, 6))


@st.composite
def family(draw: st.DrawFn) -> dict[str, Any]:
    """Two or three events over kinds p/q with a parameter x, random constraints, forbidden."""
    n = draw(st.integers(2, 3))
    events = []
    for i in range(n):
        ev: dict[str, Any] = {"name": f"e{i}", "event": draw(st.sampled_from(["p", "q"]))}
        if draw(st.booleans()):
            ev["args"] = ["x"]
        if draw(st.booleans()):
            ev["to"] = draw(st.integers(0, 1))
        events.append(ev)
    constraints = []
    for i, j in itertools.combinations(range(n), 2):
        lo, hi = draw(bounds), draw(bounds)
        if lo is not None and hi is not None and lo > hi:
            lo, hi = hi, lo
        if lo is not None or hi is not None:
            constraints.append({"start": f"e{i}", "end": f"e{j}", "lo": lo, "hi": hi})
    forbidden = []
    if draw(st.booleans()):
        f: dict[str, Any] = {"event": "r", "start": f"e{draw(st.integers(0, n - 1))}"}
        if draw(st.booleans()):
            f["end"] = f"e{draw(st.integers(0, n - 1))}"
            if f["end"] == f["start"]:
                f["end"] = f"e{(int(f['start'][1]) + 1) % n}"
        else:
            f["lo"] = draw(st.integers(0, 2))
            f["hi"] = f["lo"] + draw(st.integers(0, 3))
        forbidden.append(f)
    return {"name": "c", "events": events, "constraints": constraints, "forbidden": forbidden}


event_seq = st.lists(
    st.tuples(
        st.sampled_from(["p", "q", "r"]), st.integers(0, 2), st.integers(0, 1), st.integers(0, 1)
    ),
    max_size=9,
)


@settings(max_examples=400)
@given(family(), event_seq)
def test_online_recognition_equals_brute_force(spec: dict[str, Any], raw: list[Any]) -> None:
    try:
        compile_chronicle(spec)
    except ChronicleError:
        return  # an inconsistent random network: nothing to compare
    t = 0
    events: list[Event] = []
    for kind, dt, x, v in raw:
        t += dt * S
        events.append((kind, t, {"x": x}, 1 - v, v))
    assert keyed(recognize_all(spec, events)) == brute_force(spec, events)


def test_verdict_streams_and_held_recognitions_are_flushed_by_the_clock() -> None:
    clock = ManualClock()
    inst = DyKnowInstance(clock=clock)
    verdict = inst.add_source("verdicts/safe")  # a monitor's verdicts: plain booleans
    alarm = inst.add_source("alarm")
    proc = add_chronicle(
        inst,
        {
            "name": "recovered",
            "events": [
                {"name": "lost", "event": "safe", "from": True, "to": False},
                {"name": "back", "event": "safe", "from": False, "to": True},
            ],
            "constraints": [{"start": "lost", "end": "back", "lo": 0, "hi": 10}],
            "forbidden": [{"event": "alarm", "start": "back", "lo": 0, "hi": 5}],
        },
        {"safe": "verdicts/safe", "alarm": "alarm"},
    )
    for t, v in [(0, True), (1, False), (4, True)]:
        verdict.push(v, t * S, t * S)
    out = inst.stream("chronicles/recovered")
    assert list(out.cache.samples()) == []  # no alarm for 5 s after "back" yet
    clock.set(9 * S)
    assert proc.flush() == 1  # the instance clock is the default
    [(rec, tv, ta)] = list(out.cache.samples())
    assert rec.times == {"lost": 1 * S, "back": 4 * S} and tv == 4 * S and ta == 9 * S
    # a second loss and recovery, this time with an alarm inside the window
    for t, v in [(10, False), (12, True)]:
        verdict.push(v, t * S, t * S)
    alarm.push("smoke", 13 * S, 13 * S)
    assert proc.flush(30 * S) == 0
    assert proc.describe()["killed"] >= 1
