"""The examples run as the README says, and show what they claim to show."""

from examples import local_pipeline


async def test_local_pipeline_demo_runs_and_fills_the_gps_tunnel(capsys) -> None:  # type: ignore[no-untyped-def]
    metrics = await local_pipeline.run(pace=0)
    out = capsys.readouterr().out
    # one odometer reading per simulated second, tunnel included: the periodic policy's
    # late='approximate' filled the seconds the GPS was silent
    assert metrics["car5/odometer"]["samples_in"] == int(local_pipeline.DRIVE_S)
    # glitches (out of bounds) and stale readings (over max delay) never reach the smoother
    assert metrics["car5/speed"]["dropped"] > 0
    assert metrics["car5/speed_smooth"]["samples_in"] < metrics["car5/speed"]["samples_in"]
    assert "speeding" in out
    assert "process failures: 0" in out


async def test_two_platforms_example_answers_through_the_interface_agents(capsys) -> None:  # type: ignore[no-untyped-def]
    from examples import two_platforms

    result = await two_platforms.run()
    assert result["answer"] == {"asked": {"where": "area X"}, "wind_m_s": 4.2}
    # the request was authenticated and access-checked on uav-a before the agent saw it
    assert result["audit"]["accepted"] >= 1
    assert result["audit"]["dropped"] == 0
    assert "wind" in capsys.readouterr().out
