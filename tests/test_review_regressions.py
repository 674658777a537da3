"""Regressions for bugs a code review confirmed: each test failed before its fix."""

from __future__ import annotations

import asyncio

from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock, Policy
from dyknow_core._filter import MAX_GRID_BURST

S = NS_PER_S


async def test_periodic_subscription_with_end_and_max_delay_ends_on_the_clock() -> None:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as dk:
        src = dk.add_source("x")
        sub = dk.subscribe(
            "x",
            Policy(sample_period=1.0, approximation="most_recent", max_delay=0.5, end=3 * S),
        )
        src.push(1.0, 0, 0)
        clock.set(10 * S)  # no more data: time alone passes `end`
        got = [s.valid_time async for s in sub]  # ends instead of waiting for ever
        assert got == [0, 1 * S, 2 * S, 3 * S]
        assert sub.closed and sub.deadline() is None


def test_a_gap_in_the_data_never_floods_a_fine_grid() -> None:
    dk = DyKnowInstance(clock=ManualClock())
    src = dk.add_source("x")
    out: list = []
    sub = dk.subscribe(
        "x",
        Policy(sample_period=1e-6, approximation="most_recent", buffer_size=100),
        callback=out.extend,
    )
    src.push(1.0, 0, 0)
    src.push(2.0, S, S)  # 1 s later: 999 999 grid points in between
    # at most MAX_GRID_BURST of them (whatever the buffer), plus the two exact hits;
    # the rest counted
    assert len(out) == 1 + MAX_GRID_BURST + 1
    assert sub.filter.stats.skipped == 999_999 - MAX_GRID_BURST
    assert out[-1][0] == 2.0


def test_replacing_a_periodic_policy_keeps_the_sample_waiting_for_the_next_grid_point() -> None:
    dk = DyKnowInstance(clock=ManualClock())
    src = dk.add_source("x")
    p = Policy(sample_period=1.0, approximation="most_recent")
    unchanged, replaced = dk.subscribe("x", p), dk.subscribe("x", p)
    src.push(0.0, 0, 0)
    src.push(5.0, S // 2, S // 2)  # the newest before grid point 1 s
    replaced.replace_policy(p)
    src.push(9.0, 3 * S // 2, 3 * S // 2)  # decides grid point 1 s
    assert [tuple(s[:2]) for s in replaced.buffer] == [(0.0, 0), (5.0, S)]
    assert list(replaced.buffer) == list(unchanged.buffer)


def test_a_failing_subscriber_does_not_starve_the_others() -> None:
    dk = DyKnowInstance(clock=ManualClock())
    src = dk.add_source("x")

    def broken(batch: list) -> None:  # type: ignore[type-arg]
        raise RuntimeError("subscriber bug")

    dk.subscribe("x", callback=broken)
    other = dk.subscribe("x")
    src.push(1.0)  # the producer is not told of a consumer's bug
    assert len(other.buffer) == 1
    assert dk.failure_count == 1 and "subscriber bug" in dk.failures[-1].error


def test_a_sentinel_valid_time_is_accepted_like_any_other() -> None:
    dk = DyKnowInstance(clock=ManualClock())
    src = dk.add_source("x")
    sub = dk.subscribe("x")
    src.push(1.0, -(2**63), 0)  # "no time" from another language: ta - tv >= 2**63
    assert len(sub.buffer) == 1 and len(dk.stream("x").cache) == 1


async def test_instance_loop_is_not_blocked_by_one_push_after_a_gap() -> None:
    # the same fine grid inside a running instance: the event loop stays responsive
    async with DyKnowInstance(clock=ManualClock()) as dk:
        src = dk.add_source("x")
        dk.subscribe("x", Policy(sample_period=1e-9, approximation="most_recent"))
        src.push(1.0, 0, 0)
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        src.push(2.0, 10_000_000, 10_000_000)
        assert loop.time() - t0 < 1.0


def test_another_platform_cannot_ask_for_a_grid_finer_than_a_millisecond() -> None:
    import pytest
    from pydantic import ValidationError

    from federation._gateway_service import PolicySpec
    from federation._service_content import CreateStream

    with pytest.raises(ValidationError, match="sample-period"):
        CreateStream.model_validate(
            {"action": "create-stream", "labels": ["car5-state"], "sample-period": 1e-9}
        )
    with pytest.raises(ValidationError, match="sample_period"):
        PolicySpec(sample_period=1e-9)
    assert PolicySpec(sample_period=0.001).to_policy(0).sample_period == 0.001
