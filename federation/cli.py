"""The ``dyknow`` command: a dispatcher over subcommands (``monitor``, ``kpl``)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from dyknow_core import _kpl_cli, _monitor_cli


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the command line and run the chosen subcommand; the exit code."""
    parser = argparse.ArgumentParser(prog="dyknow", description="DyKnow Federation tools")
    sub = parser.add_subparsers(dest="command", required=True)
    mon = sub.add_parser("monitor", help="run an MTL formula over a recorded JSON-lines trace")
    _monitor_cli.add_arguments(mon)
    kpl = sub.add_parser("kpl", help="KPL files: 'dyknow kpl check FILE'")
    _kpl_cli.add_arguments(kpl)
    args = parser.parse_args(argv)
    if args.command == "monitor":
        return _monitor_cli.run(args)
    if args.command == "kpl":
        return _kpl_cli.run(args)
    parser.error(f"unknown command {args.command!r}")  # pragma: no cover - argparse refuses
    return 2  # pragma: no cover


if __name__ == "__main__":
    sys.exit(main())
