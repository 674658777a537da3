"""Process refinement: delay and backlog monitors degrade and restore subscriptions and units."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import pytest

from dyknow_core._exceptions import PolicyError, UnknownLabelError
from dyknow_core._instance import DyKnowInstance
from dyknow_core._policy import Policy
from dyknow_core._process import ComputationalUnit, Source
from dyknow_core._time import NS_PER_S, ManualClock, seconds_to_ns
from dyknow_core.reasoning import (
    FocusOfAttention,
    Refinement,
    RefinementProcess,
    add_refinement,
    is_suspended,
)

S = NS_PER_S
BASE = 1000 * S
STEP = S // 10  # the source publishes at 10 Hz


def make() -> tuple[DyKnowInstance, ManualClock, Source, list[Any]]:
    """An instance with a source ``pos`` and a unit ``track`` copying it to ``track``."""
    clock = ManualClock(BASE)
    inst = DyKnowInstance(clock=clock)
    src = inst.add_source("pos", value_type=float)
    inst.add_cu("track", lambda x: x, ["pos"], "track")
    out: list[Any] = []
    inst.subscribe("track", callback=out.extend)
    return inst, clock, src, out


def publish(clock: ManualClock, src: Source, n: int, delay: float) -> None:
    """``n`` samples at 10 Hz, each available ``delay`` seconds after its valid time."""
    for _ in range(n):
        tv = clock.now()
        src.push(float(tv), tv, tv + seconds_to_ns(delay))
        clock.advance(STEP)


def unit(inst: DyKnowInstance, name: str) -> ComputationalUnit:
    proc = inst.processes[name]
    assert isinstance(proc, ComputationalUnit)
    return proc


def events(inst: DyKnowInstance, label: str) -> list[dict[str, Any]]:
    return [s[0] for s in inst.stream(label).cache.samples()]


def states(inst: DyKnowInstance, label: str = "events/refinement/r") -> list[str]:
    return [e["state"] for e in events(inst, label)]


async def until(pred: Callable[[], bool], rounds: int = 200) -> None:
    """Let the event loop run until ``pred`` holds (bounded: no wall-clock sleeps)."""
    for _ in range(rounds):
        if pred():
            return
        await asyncio.sleep(0)
    raise AssertionError("condition not reached")


DELAY_RULE: dict[str, Any] = {
    "name": "r",
    "stream": "pos",
    "statistic": "p90",
    "window": 1.0,
    "threshold": 0.2,
    "restore_below": 0.05,
    "hold": 1.0,
    "lower_rate": [{"process": "track", "sample_period": 1.0}],
}


async def test_rising_delay_degrades_and_falling_delay_restores() -> None:
    inst, clock, src, out = make()
    async with inst:
        proc = add_refinement(inst, DELAY_RULE)
        assert isinstance(proc, RefinementProcess) and FocusOfAttention is RefinementProcess
        assert proc.label == "events/refinement/r"
        sub = unit(inst, "track").subscriptions[0]
        original = sub.policy

        publish(clock, src, 20, 0.01)
        assert not proc.degraded and states(inst) == []
        assert len(out) == 20

        publish(clock, src, 20, 0.5)  # latency grew
        assert proc.degraded
        assert sub.policy.sample_period == 1.0
        assert sub.policy.replace(sample_period=None) == original  # only the rate changed
        [ev] = events(inst, "events/refinement/r")
        assert ev["state"] == "degraded" and ev["metric"] == "delay_p90"
        assert ev["target"] == "pos" and ev["value"] > 0.2

        before = len(out)
        publish(clock, src, 30, 0.5)
        assert len(out) - before <= 4  # one a second instead of ten

        # back under the lower threshold: restored only once it has held for a second
        publish(clock, src, 12, 0.01)  # the window still holds some late samples
        assert proc.degraded
        publish(clock, src, 10, 0.01)
        assert proc.degraded  # below since less than the hold time
        publish(clock, src, 5, 0.01)
        assert not proc.degraded
        assert sub.policy == original
        assert states(inst) == ["degraded", "restored"]
        assert events(inst, "events/refinement/r")[-1]["value"] < 0.05
        before = len(out)
        publish(clock, src, 10, 0.01)
        assert len(out) - before == 10


async def test_no_flapping_around_the_threshold() -> None:
    inst, clock, src, _ = make()
    async with inst:
        rule = {**DELAY_RULE, "statistic": "max", "window": 0.15, "threshold": 0.1}
        proc = add_refinement(inst, rule)
        for _ in range(10):  # just above, then between the thresholds, over and over
            publish(clock, src, 3, 0.11)
            publish(clock, src, 3, 0.08)
        assert states(inst) == ["degraded"]
        for _ in range(5):  # dips below the lower threshold shorter than the hold time
            publish(clock, src, 5, 0.01)
            publish(clock, src, 1, 0.08)
        assert states(inst) == ["degraded"] and proc.degraded
        publish(clock, src, 15, 0.01)
        assert states(inst) == ["degraded", "restored"]


async def test_mean_statistic_and_describe() -> None:
    inst, clock, src, _ = make()
    async with inst:
        proc = add_refinement(inst, {**DELAY_RULE, "statistic": "mean", "threshold": 0.3})
        publish(clock, src, 10, 0.2)
        publish(clock, src, 3, 0.6)
        assert not proc.degraded  # mean ≈ 0.29 over the last second
        publish(clock, src, 1, 0.6)
        assert proc.degraded
        d = proc.describe()
        assert (
            d["state"] == "degraded" and d["metric"] == "delay_mean" and d["kind"] == "refinement"
        )
        assert d["last_value"] == pytest.approx(0.32, abs=0.02)


async def test_a_subscription_given_directly_is_degraded_and_restored() -> None:
    inst, clock, src, _ = make()
    async with inst:
        app = inst.subscribe("pos")
        rule = {**DELAY_RULE, "lower_rate": [], "suspend": ["track"]}
        proc = add_refinement(inst, rule, subscriptions={app: {"sample_period": 2.0}})
        publish(clock, src, 10, 0.5)
        assert app.policy.sample_period == 2.0 and is_suspended(unit(inst, "track"))
        # a policy someone else put in meanwhile is not overridden by the restore
        app.replace_policy(Policy(order="strict"))
        publish(clock, src, 30, 0.0)
        assert not proc.degraded and app.policy == Policy(order="strict")


async def test_removing_the_process_restores_everything() -> None:
    inst, clock, src, out = make()
    async with inst:
        inst.add_cu("low", lambda x: x + 1, ["pos"], "low")
        rule = {**DELAY_RULE, "suspend": ["low"]}
        add_refinement(inst, rule, output="attention")
        sub = unit(inst, "track").subscriptions[0]
        observed = inst.stream("pos").stats()["subscribers"]
        publish(clock, src, 10, 0.5)
        low = unit(inst, "low")
        assert is_suspended(low)
        n_low = len(inst.stream("low").cache)
        publish(clock, src, 5, 0.5)
        assert len(inst.stream("low").cache) == n_low  # a suspended unit computes nothing

        inst.remove_process("refinement:r")
        assert sub.policy == Policy()
        assert not is_suspended(low)
        assert not inst.has_label("attention")
        assert inst.stream("pos").stats()["subscribers"] == observed - 1  # no observer left
        publish(clock, src, 3, 0.5)
        assert len(inst.stream("low").cache) == n_low + 3  # resumed with new samples only
        assert len(out) >= 3


async def test_periodic_evaluation_restores_when_the_stream_goes_quiet() -> None:
    inst, clock, src, _ = make()
    async with inst:
        proc = add_refinement(inst, {**DELAY_RULE, "period": 0.5})
        publish(clock, src, 10, 0.5)
        assert proc.degraded
        await until(lambda: clock._sleepers != [])  # the loop waits on the instance clock
        clock.advance(2 * S)  # nothing published: the window empties
        await until(lambda: proc._below_since is not None)
        assert proc.degraded
        clock.advance(S)  # the hold time is over
        await until(lambda: not proc.degraded)
        assert states(inst) == ["degraded", "restored"]


async def test_backlog_suspends_a_low_priority_unit_and_resumes_it() -> None:
    clock = ManualClock(BASE)
    inst = DyKnowInstance(clock=clock)
    gate = asyncio.Event()

    async def heavy(x: float) -> float:
        await gate.wait()
        return x

    async with inst:
        src = inst.add_source("in", value_type=float)
        side = inst.add_source("side", value_type=float)
        inst.add_cu("heavy", heavy, ["in"], "heavy")
        inst.add_cu("low", lambda x: x * 2, ["side"], "low")
        rule = {
            "name": "r",
            "unit": "heavy",
            "threshold": 5,
            "restore_below": 1,
            "hold": 0.5,
            "period": 0.1,
            "suspend": ["low"],
        }
        proc = add_refinement(inst, rule)
        low = unit(inst, "low")
        for k in range(10):
            src.push(float(k), BASE + k, BASE + k)
        assert proc.degraded and is_suspended(low)
        [ev] = events(inst, "events/refinement/r")
        assert ev["metric"] == "backlog" and ev["target"] == "heavy" and ev["value"] > 5
        side.push(1.0)
        assert len(inst.stream("low").cache) == 0

        gate.set()
        await until(lambda: len(inst.stream("heavy").cache) == 10)
        await until(lambda: clock._sleepers != [])
        clock.advance(seconds_to_ns(0.1))
        await until(lambda: proc._below_since is not None)
        clock.advance(seconds_to_ns(0.5))
        await until(lambda: not proc.degraded)
        assert not is_suspended(low)
        assert states(inst) == ["degraded", "restored"]
        side.push(2.0)
        assert [s[0] for s in inst.stream("low").cache.samples()] == [4.0]


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"name": "r", "stream": "pos", "threshold": 1}, "lower_rate"),
        ({**DELAY_RULE, "unit": "track"}, "stream"),
        ({**DELAY_RULE, "stream": None}, "stream"),
        ({**DELAY_RULE, "restore_below": 0.5}, "restore_below"),
        ({**DELAY_RULE, "window": 0}, "window"),
        ({**DELAY_RULE, "hold": -1}, "hold"),
        ({**DELAY_RULE, "period": 0}, "period"),
        ({**DELAY_RULE, "threshold": float("nan")}, "threshold"),
        ({**DELAY_RULE, "statistic": "p42"}, "statistic"),
        ({**DELAY_RULE, "name": " "}, "name"),
        ({**DELAY_RULE, "colour": "red"}, "colour"),
        ({**DELAY_RULE, "lower_rate": [{"process": "track"}]}, "lower_rate.0.policy"),
        (
            {**DELAY_RULE, "lower_rate": [{"process": "track", "sample_period": -1}]},
            "lower_rate.0.sample_period",
        ),
    ],
)
def test_bad_refinements_are_refused_naming_the_field(data: dict[str, Any], field: str) -> None:
    with pytest.raises(PolicyError) as err:
        Refinement.parse(data)
    assert err.value.field == field


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"lower_rate": [{"process": "nobody", "sample_period": 1}]}, "lower_rate.0.process"),
        ({"lower_rate": [{"process": "source:pos", "sample_period": 1}]}, "lower_rate.0.process"),
        (
            {"lower_rate": [{"process": "track", "input": "x", "sample_period": 1}]},
            "lower_rate.0.input",
        ),
        (
            {"lower_rate": [{"process": "label", "policy": {"lower": 0}}]},
            "lower_rate.0.policy.lower",
        ),
        ({"suspend": ["nobody"]}, "suspend.0"),
        ({"stream": None, "unit": "source:pos"}, "unit"),
    ],
)
async def test_refinements_that_do_not_fit_the_instance_are_refused(
    changes: dict[str, Any], field: str
) -> None:
    inst, *_ = make()
    async with inst:
        inst.add_source("names", value_type=str)
        inst.add_cu("label", str, ["names"], "labels")
        with pytest.raises(PolicyError) as err:
            add_refinement(inst, {**DELAY_RULE, **changes})
        assert err.value.field == field
        assert not inst.has_label("events/refinement/r")
        assert "refinement:r" not in inst.processes


async def test_unknown_stream_and_duplicate_names_are_refused() -> None:
    inst, *_ = make()
    async with inst:
        with pytest.raises(UnknownLabelError):
            add_refinement(inst, {**DELAY_RULE, "stream": "nowhere"})
        add_refinement(inst, DELAY_RULE)
        with pytest.raises(Exception, match="exists already"):
            add_refinement(inst, DELAY_RULE)


async def test_a_unit_both_slowed_and_suspended_resumes_at_its_original_rate() -> None:
    inst, clock, src, out = make()
    async with inst:
        proc = add_refinement(inst, {**DELAY_RULE, "suspend": ["track"]})
        track = unit(inst, "track")
        publish(clock, src, 10, 0.5)
        assert proc.degraded and is_suspended(track)
        n = len(out)
        publish(clock, src, 30, 0.0)
        assert not proc.degraded and not is_suspended(track)
        assert track.subscriptions[0].policy == Policy()
        assert len(out) > n
        n = len(out)
        publish(clock, src, 10, 0.0)
        assert len(out) == n + 10
