"""Run benchmarks: ``python -m bench`` runs all, ``python -m bench <name> …`` some.

Arguments starting with ``-`` are options for the benchmarks, not names: they stay in
``sys.argv`` for a benchmark to read (``python -m bench scale --quick``). ``-h`` or
``--help`` prints what each named benchmark (all when none is named) measures and its
options, and runs nothing.

A benchmark is any public module of this package with a ``run()`` function, so adding one
is adding a file; nothing here needs to know its name.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
import time

import bench


def available() -> list[str]:
    """Names of the benchmark modules in this package, sorted."""
    return sorted(
        m.name
        for m in pkgutil.iter_modules(bench.__path__)
        if not m.name.startswith("_") and not m.ispkg
    )


def main(argv: list[str]) -> int:
    """Run the named benchmarks (all when none are named); 2 on an unknown name."""
    names = available()
    wanted = [a for a in argv if not a.startswith("-")] or names
    unknown = [n for n in wanted if n not in names]
    if unknown:
        print(
            f"unknown benchmark {', '.join(map(repr, unknown))}; available: {', '.join(names)}",
            file=sys.stderr,
        )
        return 2
    if "-h" in argv or "--help" in argv:
        for name in wanted:
            doc = importlib.import_module(f"bench.{name}").__doc__ or "(no description)"
            print(f"== bench {name}\n{doc.strip()}\n")
        return 0
    for name in wanted:
        module = importlib.import_module(f"bench.{name}")
        if not callable(getattr(module, "run", None)):
            print(f"bench.{name} has no run() function", file=sys.stderr)
            return 2
        print(f"== bench {name}", flush=True)
        t0 = time.perf_counter()
        module.run()
        print(f"== bench {name} took {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
