"""Files a user loads, crafted to break the process that reads them: each is named, no crash.

A KPL application, a platform config, a vocabulary: each read by a real ``dyknow``
process, as a user runs it. A file that is wrong must end the command with exit 2 and a
line naming the file (and the line and column, for KPL) and what is wrong, never a
traceback: a formula nested past Python's stack, a window of 1e300 s, a config that is
not UTF-8 or nests its arrays past the TOML reader's stack.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from _node_example import Station, _samples, _stats

from tests.test_console_access import write_operator

ROOT = Path(__file__).resolve().parent.parent


def dyknow(*args: str | Path) -> subprocess.CompletedProcess[str]:
    """``dyknow ARGS`` in a process of its own; its exit code, stdout and stderr."""
    return subprocess.run(
        [sys.executable, "-m", "federation.cli", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )


def monitor(formula: str) -> str:
    return f'source a\nmonitor m = "{formula}" every 1 with {{a: a}}\n'


@pytest.mark.parametrize(
    ("text", "want"),
    [
        (monitor("not " * 20_000 + "a > 1"), "2:"),
        (monitor("(" * 3_000 + "a > 1" + ")" * 3_000), "2:"),
        (monitor("a > 1 or " * 3_000 + "a > 1"), "2:"),  # a chain: Or(Or(Or(…)))
        (monitor("a > 1 until[0,1] " * 3_000 + "a > 1"), "2:"),
        (monitor("always[0,1] " * 5_000 + "a > 1"), "2:"),
    ],
    ids=["not", "parentheses", "or-chain", "until-chain", "always"],
)
def test_a_formula_nested_past_the_stack_is_a_kpl_error(
    tmp_path: Path, text: str, want: str
) -> None:
    app = tmp_path / "deep.kpl"
    app.write_text(text)
    r = dyknow("kpl", "check", app)
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert f"{app}:{want}" in r.stderr and "nested deeper than 64 levels" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_a_formula_as_deep_as_a_person_writes_one_still_parses(tmp_path: Path) -> None:
    app = tmp_path / "ok.kpl"
    app.write_text(monitor("(" * 20 + "a > 1" + ")" * 20 + " or a > 2" * 40))
    r = dyknow("kpl", "check", app)
    assert r.returncode == 0 and "ok: 2 declarations" in r.stdout, r.stderr


@pytest.mark.parametrize("bound", ["1e300", "1e10"])
def test_a_chronicle_window_beyond_any_time_line_is_a_kpl_error(tmp_path: Path, bound: str) -> None:
    app = tmp_path / "chronicle.kpl"
    app.write_text(
        "source a\nchronicle c {\n    input x = a\n    event e = x from true to false\n"
        f"    event f = x from false to true\n    constraint e -> f in [0, {bound}]\n}}\n"
    )
    r = dyknow("kpl", "check", app)
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert f"{app}:6:" in r.stderr and "constraints.0.hi" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("which", ["config", "vocabulary"])
@pytest.mark.parametrize(
    ("content", "want"),
    [
        (b'name = "x"\n# \xff\xfe\n', "not UTF-8 text"),
        (
            b'name = "x"\nq = ' + b"[" * 5_000 + b"]" * 5_000 + b"\n",
            "not valid TOML: nested too deep",
        ),
    ],
    ids=["not-utf8", "deep-arrays"],
)
def test_a_config_or_vocabulary_that_breaks_the_toml_reader_is_named(
    tmp_path: Path, which: str, content: bytes, want: str
) -> None:
    config = write_operator(tmp_path)
    bad = config if which == "config" else tmp_path / "vocabulary.toml"
    bad.write_bytes(content)
    r = dyknow("node", "--config", config)
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert f"{bad}: {want}" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.timeout(120)
def test_a_line_nested_past_the_stack_is_one_bad_message_of_a_file_input(tmp_path: Path) -> None:
    # examples/node's station replaying its JSON-lines file, a hostile line first: the
    # JSON reader's RecursionError ended the whole input (nothing of the file replayed)
    station = Station(tmp_path)
    try:
        jsonl = station.dir / "observations.jsonl"
        jsonl.write_text("[" * 100_000 + "]" * 100_000 + "\n" + jsonl.read_text())
        station.start("file")
        station.latest(
            "temperature", until=lambda a: _samples(a, "temperature")[0][0] == 19.5
        )  # the file's last line: every line after the hostile one replayed
        out, err = station.stop()
    finally:
        station.stop()
    [row] = [r for r in _stats(out) if str(r.get("input", "")).endswith("observations.jsonl")]
    assert row["bad"] == {"bad-time": 1, "not-json": 1} and row["samples"] == 20, row
    assert "line 1: nested too deep" in err and "Traceback" not in err
