"""The ``dyknow`` command's entry point: ``dyknow node`` without typer, the rest with it.

The commands themselves, their options and help are the typer app of
``federation._cli_app``. A plain ``dyknow node -c FILE`` is run without importing it
(``federation._cli_node``): typer and the other commands would stay in the node's
memory for as long as it runs.
"""

from __future__ import annotations

import errno
import sys
from collections.abc import Sequence
from typing import Any, TextIO


class _Pacified:
    """A standard stream whose flush ignores a reader gone away (EPIPE), as click's does."""

    def __init__(self, wrapped: TextIO) -> None:
        self._wrapped = wrapped

    def flush(self) -> None:
        try:
            self._wrapped.flush()
        except OSError as exc:
            if exc.errno != errno.EPIPE:
                raise

    def __getattr__(self, name: str) -> Any:
        return getattr(self._wrapped, name)


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the command line and run the chosen subcommand; the exit code."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args[:1] in (["node"], ["console"], ["foxglove"]):
        from ._hup import hold_hup

        # first, before any heavy import (the package imports nothing until used): a
        # SIGHUP while the platform starts must not end it (it reloads once ready)
        hold_hup()
    from ._cli_node import node_config, run_node

    config = node_config(args)
    if config is not None:
        try:
            return run_node(config)
        except KeyboardInterrupt:  # as typer answers it
            return 130
        except OSError as exc:
            if exc.errno != errno.EPIPE:
                raise
            # what typer answers: the reader of our output went away; 1, without a word
            # (and without the interpreter's own complaint when it flushes at exit)
            sys.stdout = _Pacified(sys.stdout)
            sys.stderr = _Pacified(sys.stderr)
            return 1
    from ._cli_app import app

    try:
        app(args=args, prog_name="dyknow")
    except SystemExit as exc:
        if exc.code is None or isinstance(exc.code, int):
            return int(exc.code or 0)
        print(exc.code, file=sys.stderr)
        return 1
    return 0  # pragma: no cover - typer always exits in standalone mode


if __name__ == "__main__":
    sys.exit(main())
