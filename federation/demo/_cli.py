"""``dyknow demo traffic``: the typer command group of the demo."""

from __future__ import annotations

import asyncio
import json
import os
import signal
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

if TYPE_CHECKING:
    from rich.console import Console

__all__ = ["demo_app"]


def _console(**options: Any) -> Console:
    """A rich console (rich is imported when a demo runs, not with the ``dyknow`` command)."""
    from rich.console import Console

    return Console(**options)


demo_app = typer.Typer(help="Demos: 'dyknow demo traffic' (multi-UAV traffic monitoring).")


@demo_app.command("traffic")
def traffic(
    uavs: Annotated[int, typer.Option("--uavs", min=1, max=8, help="UAV processes")] = 3,
    duration: Annotated[
        float, typer.Option("--duration", min=20.0, help="seconds of simulated traffic")
    ] = 60.0,
    seed: Annotated[int, typer.Option("--seed", help="the simulated world's seed")] = 1,
    speed: Annotated[
        float, typer.Option("--speed", min=0.25, max=8.0, help="simulated seconds per second")
    ] = 2.0,
    port: Annotated[
        int, typer.Option("--port", help="the operator console's port (0: any)")
    ] = 8080,
    host: Annotated[str, typer.Option("--host", help="the console's address")] = "127.0.0.1",
    no_console: Annotated[bool, typer.Option("--no-console", help="no web console")] = False,
    foxglove_port: Annotated[
        int | None,
        typer.Option(
            "--foxglove-port",
            help="the operator also serves Foxglove on this WebSocket port (0: any; "
            "docs/foxglove.md)",
        ),
    ] = None,
    allow_host: Annotated[
        list[str] | None,
        typer.Option(
            "--allow-host",
            help="a host name the console may be reached by, besides localhost and IP "
            "addresses (repeatable)",
        ),
    ] = None,
    hold: Annotated[
        float, typer.Option("--hold", min=0.0, help="keep the console open S s after the report")
    ] = 0.0,
    run_dir: Annotated[
        Path | None, typer.Option("--run-dir", help="keep keys and configs here (default: temp)")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print the report as JSON")] = False,
) -> None:
    """Several UAV processes monitor simulated traffic; the operator gets the global picture."""
    from ..console import allowed_names, configured_token
    from ._run import DemoOptions, run_traffic_demo

    try:
        # $DYKNOW_CONSOLE_TOKEN, else a random one: the URL printed carries it
        token = configured_token(None)
        hosts = tuple(allowed_names(allow_host or [], os.environ))
    except ValueError as exc:
        _console(stderr=True).print(f"dyknow demo traffic: {exc}", markup=False)
        raise typer.Exit(2) from None
    options = DemoOptions(
        uavs=uavs,
        duration=duration,
        seed=seed,
        speed=speed,
        console=not no_console,
        host=host,
        port=port,
        run_dir=None if run_dir is None else str(run_dir),
        hold=hold,
        console_token=token,
        allow_hosts=hosts,
        foxglove_port=foxglove_port,
    )
    out = _console(highlight=False, soft_wrap=True)
    say = (lambda _: None) if as_json else (lambda text: out.print(text, markup=False))
    # SIGTERM (timeout, docker stop, a closed CI job) takes Ctrl-C's way out, so the UAV
    # processes are stopped too; asyncio.run would otherwise die without cleaning up
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        report = asyncio.run(run_traffic_demo(options, say))
    except KeyboardInterrupt:
        raise typer.Exit(130) from None
    except (TimeoutError, RuntimeError, OSError) as exc:
        _console(stderr=True).print(f"dyknow demo traffic: {exc}", markup=False)
        raise typer.Exit(1) from None
    if as_json:
        print(json.dumps(report.to_dict(), indent=1, default=str))
    missed = sum(1 for _, f in report.matched if f is None)
    raise typer.Exit(0 if missed == 0 and not report.false_positives else 3)
