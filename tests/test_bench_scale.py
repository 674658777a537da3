"""The scale benchmark (``python -m bench scale``) run small, so it cannot rot unnoticed.

Three UAV platforms in two spawned worker processes plus the operator here, two streams
each at 10 Hz for 3 s: every UAV joins, every global query is answered by all of them,
every sample pushed arrives, and the BENCH lines come out in the form CI greps for.
"""

from __future__ import annotations

import json
import re

import pytest

from bench import __main__ as bench_main
from bench.scale import ScaleResult, measure, print_result

BENCH_LINE = re.compile(
    r"^BENCH [a-z0-9-]+ ours=\S+ [a-z0-9-]+=\S+ ratio=\d+\.\d\d unit=\S+ better=(higher|lower)$"
)


@pytest.fixture(scope="module")
def small() -> ScaleResult:
    """One small run shared by the tests below (spawning platforms is the slow part)."""
    return measure(platforms=3, streams=2, hz=10.0, seconds=3.0, workers=2, queries=10, probe=True)


@pytest.mark.timeout(60)
def test_small_run_joins_answers_and_loses_nothing(small: ScaleResult) -> None:
    r = small
    assert r.workers == 2
    assert 0 < r.join < 30 and 0 < r.bare_join < 30
    assert len(r.open_to_joined) == 3 and len(r.spawn_to_imported) == 2
    assert len(r.query_ms) == 10 and r.query_failures == []
    assert len(r.idle_ms) == 10  # the same query before the exports flow
    assert len(r.raw_ms) == 10 and r.raw_failures == 0
    # every UAV answered each global get-latest as it came (`answer_at_once`), over real
    # zenoh between processes; the create-stream of each went through its handler
    assert r.at_once >= 3 * (len(r.query_ms) + len(r.idle_ms))
    assert r.handled >= r.at_once + 3
    # 3 UAVs x 2 streams x 10 Hz over at least the 3 s window
    assert r.counted >= 3 * 2 * 10 * 3 * 0.8
    assert r.counted == r.expected and r.lost == 0
    assert r.never_arrived == 0 and r.duplicates == 0 and r.import_lost == 0
    assert 0 < len(r.e2e_ms) <= r.counted and min(r.e2e_ms) >= 0
    assert r.cpu_operator > 0 and r.cpu_workers > 0
    # the loop thread's from /proc (10 ms ticks), the process's from rusage: a tick apart
    assert 0 < r.cpu_operator_loop <= r.cpu_operator + 0.02 / r.window
    assert 0 < r.cpu_workers_loop <= r.cpu_workers
    assert r.rss_operator > 0 and len(r.rss_workers) == 2 and len(r.rss_bare_workers) == 2
    # the loop-lag probes ran in every worker and at the operator: each kind counted
    for probe in (r.worker_probe, r.operator_probe):
        assert set(probe) == {f"{k}>{ms}" for k in ("busy", "core", "gil") for ms in (5, 20)} | {
            "worst"
        }
        assert len(probe["worst"]) == 3


@pytest.mark.timeout(60)
def test_bench_lines_have_the_anchored_form(
    small: ScaleResult, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = print_result(small, "scale-3")
    out = capsys.readouterr().out
    names = [line.split()[1] for line in lines]
    assert names == [
        "scale-3",
        "scale-3-query-p50",
        "scale-3-join",
        "scale-3-rss",
        "scale-3-delivered",
    ]
    for line in lines:
        assert BENCH_LINE.match(line), line
        assert line in out
    assert "ratio=1.00 unit=samples" in lines[-1]  # delivered = pushed


@pytest.mark.parametrize(
    ("kwargs", "named"),
    [
        ({"platforms": 0}, "platforms"),
        ({"streams": 0}, "streams"),
        ({"queries": 0}, "queries"),
        ({"platforms": 2, "workers": 3}, "workers"),
        ({"hz": 0.0}, "hz"),
        ({"seconds": -1.0}, "seconds"),
    ],
)
def test_bad_sizes_are_refused_by_name(kwargs: dict[str, float], named: str) -> None:
    with pytest.raises(ValueError, match=named):
        measure(**kwargs)  # type: ignore[arg-type]


def test_the_runner_knows_scale_and_leaves_options_to_it() -> None:
    assert "scale" in bench_main.available()
    assert bench_main.main(["--quick", "no-such-bench"]) == 2


def test_help_says_what_a_benchmark_measures_and_runs_nothing(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``python -m bench scale --help`` prints its description and options, not a run."""
    assert bench_main.main(["scale", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("== bench scale\n") and "--quick" in out and "--procs" in out
    assert "== bench scale took" not in out  # nothing ran


def test_the_bare_sessions_have_our_sessions_settings() -> None:
    """The join's peer is fair: every setting the bare sessions get is what ours run with."""
    from agents.transports import ZenohConfig
    from bench._scale_node import zenoh_settings

    config = ZenohConfig.loopback(0, connect=["tcp/127.0.0.1:7447"])
    ours = config.to_zenoh()
    settings = dict(zenoh_settings(config))
    assert {"transport/shared_memory/enabled", "transport/link/tx/queue/size/data"} <= set(settings)
    for path, value in settings.items():
        assert json.loads(ours.get_json(path)) == json.loads(value), path


@pytest.mark.parametrize(
    ("argv", "runs", "prefixes"),
    [
        ([], [(4, 30.0, 400), (32, 30.0, 400)], ["scale-32", "scale-32-procs"]),
        (["--quick"], [(4, 8.0, 100)], ["scale-32"]),
        (["--procs"], [(32, 30.0, 400)], ["scale-32-procs"]),
        (["--quick", "--procs"], [(32, 8.0, 100)], ["scale-32-procs"]),
    ],
)
def test_the_flags_choose_the_cases_run(
    monkeypatch: pytest.MonkeyPatch,
    argv: list[str],
    runs: list[tuple[int, float, int]],
    prefixes: list[str],
) -> None:
    """``--quick`` runs the 4-worker case only, ``--procs`` the one-process-per-UAV case only."""
    from bench import scale

    made: list[tuple[int, float, int]] = []
    printed: list[str] = []

    def fake_measure(*, seconds: float, queries: int, workers: int, probe: bool) -> ScaleResult:
        made.append((workers, seconds, queries))
        return ScaleResult(scale.PLATFORMS, scale.STREAMS, scale.HZ, workers)

    def fake_print(r: ScaleResult, prefix: str = "scale-32") -> list[str]:
        printed.append(prefix)
        return []

    monkeypatch.setattr(scale, "measure", fake_measure)
    monkeypatch.setattr(scale, "print_result", fake_print)
    monkeypatch.setattr("sys.argv", ["bench", "scale", *argv])
    scale.run()
    assert made == runs
    assert printed == prefixes
