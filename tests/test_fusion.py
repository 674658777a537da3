"""Fusion of an imported stream with a local one, preferring local samples."""

from __future__ import annotations

import pytest

from dyknow_core import NS_PER_S, DyKnowInstance, ManualClock, UnknownLabelError
from federation._fusion import add_fusion

S = NS_PER_S


async def drain(sub, n: int) -> list:  # type: ignore[no-untyped-def]
    return [await sub.get(timeout=2) for _ in range(n)]


async def test_local_samples_win_and_imported_ones_fill_the_gaps() -> None:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as dk:
        local = dk.add_source("car5/state/local")
        imported = dk.add_source("car5/state/from-uav-a")
        fusion = add_fusion(
            dk, "car5/state/local", "car5/state/from-uav-a", "car5/state", window=0.5
        )
        out = dk.subscribe("car5/state")
        # both see t=1 s; only uav-a sees t=3 s (car5 out of our camera's view)
        clock.set(1 * S + 10)
        local.push("local@1", 1 * S)
        imported.push("remote@1", 1 * S)
        clock.set(3 * S + 10)
        imported.push("remote@3", 3 * S)
        clock.set(4 * S)  # both windows have passed: the timer decides
        got = await drain(out, 2)
        assert [s.value for s in got] == ["local@1", "remote@3"]
        assert [s.valid_time for s in got] == [1 * S, 3 * S]
        assert fusion.suppressed == 1
        assert (fusion.local_emitted, fusion.imported_emitted) == (1, 1)


async def test_imported_sample_is_decided_as_soon_as_local_data_moves_past_its_window() -> None:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as dk:
        local = dk.add_source("l")
        imported = dk.add_source("i")
        add_fusion(dk, "l", "i", "o", window=0.5)
        out = dk.subscribe("o")
        imported.push("remote@1", 1 * S, 1 * S)
        local.push("local@2", 2 * S, 2 * S)  # local is past 1.5 s and saw nothing near 1 s
        got = await drain(out, 2)
        assert sorted(s.value for s in got) == ["local@2", "remote@1"]


async def test_combine_merges_instead_of_suppressing() -> None:
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as dk:
        local = dk.add_source("l")
        imported = dk.add_source("i")
        add_fusion(dk, "l", "i", "o", window=0.5, combine=lambda lv, iv: (lv + iv) / 2)
        out = dk.subscribe("o")
        local.push(10.0, 1 * S, 1 * S)
        imported.push(20.0, int(1.2 * S), int(1.2 * S))
        clock.set(2 * S)
        got = await drain(out, 2)
        assert [s.value for s in got] == [10.0, 15.0]


async def test_a_replaying_fusion_fuses_the_imported_samples_that_came_before_it() -> None:
    # platform.fuse makes the fusion once the import's first sample arrived: not lost
    clock = ManualClock()
    async with DyKnowInstance(clock=clock) as dk:
        dk.add_source("l")
        imported = dk.add_source("i")
        clock.set(1 * S)
        imported.push("remote@1", 1 * S)
        add_fusion(dk, "l", "i", "late", window=0.5)
        fusion = add_fusion(dk, "l", "i", "o", window=0.5, replay=True)
        out = dk.subscribe("o")
        clock.set(2 * S)
        imported.push("remote@2", 2 * S)
        clock.set(3 * S)
        got = await drain(out, 2)
        assert [s.value for s in got] == ["remote@1", "remote@2"]
        assert fusion.imported_emitted == 2
        assert dk.latest("late").latest.value == "remote@2"  # without replay: from now on


async def test_unknown_labels_are_refused_before_anything_is_created() -> None:
    async with DyKnowInstance(clock=ManualClock()) as dk:
        dk.add_source("l")
        with pytest.raises(UnknownLabelError):
            add_fusion(dk, "l", "nope", "o")
        assert not dk.has_label("o")
