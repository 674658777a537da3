"""``dyknow kpl check FILE``: check a KPL file and print its errors as ``FILE:LINE:COL: msg``.

Exit code 0 with ``ok: N declarations`` when the file checks, 2 otherwise. CU callables
are not imported: they are resolved when an instance is set up from the file.
"""

from __future__ import annotations

import argparse
import sys
from typing import TextIO

from .kpl import check, parse


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Add the ``kpl`` sub-subcommands (``check``) to a (sub)parser."""
    sub = p.add_subparsers(dest="kpl_command", required=True)
    c = sub.add_parser("check", help="check a KPL file; errors as FILE:LINE:COL: message")
    c.add_argument("file", help="the KPL file")


def run(args: argparse.Namespace, out: TextIO | None = None, err: TextIO | None = None) -> int:
    """Run ``dyknow kpl …`` on parsed arguments; the exit code."""
    out = out or sys.stdout
    err = err or sys.stderr
    try:
        with open(args.file, encoding="utf-8") as f:
            text = f.read()
    except OSError as exc:
        print(f"{args.file}: cannot read: {exc.strerror}", file=err)
        return 2
    except UnicodeDecodeError as exc:
        print(f"{args.file}: not UTF-8 text: {exc.reason}", file=err)
        return 2
    errors = check(text)
    if errors:
        for e in errors:
            print(e.format(args.file), file=err)
        return 2
    print(f"ok: {len(parse(text).decls)} declarations", file=out)
    return 0
