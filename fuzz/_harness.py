"""What both atheris harnesses share: seeding an empty corpus and the libFuzzer loop."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

REPORT_EVERY = 1000

T = TypeVar("T")


def write_seeds(args: list[str], seeds: list[bytes]) -> None:
    """Put ``seeds`` in the corpus directory given (the first non-option argument) if empty."""
    dirs = [Path(a) for a in args if not a.startswith("-")]
    if dirs and dirs[0].is_dir() and not any(dirs[0].iterdir()):
        for i, seed in enumerate(seeds):
            (dirs[0] / f"seed-{i}").write_bytes(seed)


def run(
    atheris: Any,
    name: str,
    make_target: Callable[[], T],
    payload_of: Callable[[T, bytes], bytes],
    seeds: list[bytes],
) -> None:
    """Run libFuzzer: each input becomes a payload fed to one target (made on first use)."""
    targets: list[Any] = []

    def test_one_input(data: bytes) -> None:
        # raises (a crash for libFuzzer) when the input was not handled
        if not targets:
            targets.append(make_target())
        target = targets[0]
        target.feed(payload_of(target, data))
        if target.inputs % REPORT_EVERY == 0:
            print(target.summary(f"{name} (atheris)"), flush=True)

    # what the platform logs below an error is not a finding: keep the fuzzer's output short
    logging.getLogger().addHandler(logging.NullHandler())
    write_seeds(sys.argv[1:], seeds)
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()
