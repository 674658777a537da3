"""Every runnable benchmark tool answers ``--help`` with what it measures and runs nothing."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TOOLS = sorted(
    p.stem
    for p in (ROOT / "bench").glob("_*.py")
    if p.stem != "__main__" and 'if __name__ == "__main__":' in p.read_text()
)


@pytest.mark.parametrize("tool", TOOLS)
def test_a_bench_tool_prints_its_description_for_help(tool: str) -> None:
    """``python -m bench.<tool> --help``: its description (or argparse's usage), exit 0."""
    done = subprocess.run(
        [sys.executable, "-m", f"bench.{tool}", "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    doc = __import__(f"bench.{tool}", fromlist=["_"]).__doc__ or ""
    first = doc.strip().splitlines()[0] if doc.strip() else "usage:"
    assert first in done.stdout or "usage:" in done.stdout, done.stdout[:500]
