"""The packages' layering as the interpreter sees it: what importing one package loads.

`lint-imports` (``make lint``) checks the import graph statically; this checks what an
import actually runs, in a fresh interpreter (this one has imported everything already).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]

# package imported -> our packages it must not load
_MUST_NOT_LOAD = {
    "agents": ("dyknow_core", "ontology", "federation"),
    "dyknow_core": ("agents", "ontology", "federation"),
    "ontology": ("agents", "federation"),
}


def _modules_after(setup: str, prefixes: tuple[str, ...]) -> list[str]:
    """The modules starting with one of ``prefixes`` loaded after ``setup`` in a new interpreter."""
    code = (
        f"import sys\n{setup}\n"
        f"print('\\n'.join(m for m in sys.modules if m.startswith({prefixes!r})))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        check=True,
    )
    return sorted(done.stdout.split())


def _loaded(package: str, prefixes: tuple[str, ...]) -> list[str]:
    """The modules starting with one of ``prefixes`` that a fresh ``import package`` loads."""
    return _modules_after(f"import {package}", prefixes)


@pytest.mark.parametrize("package", sorted(_MUST_NOT_LOAD))
def test_importing_a_package_loads_none_of_the_layers_it_must_not_know(package: str) -> None:
    forbidden = _MUST_NOT_LOAD[package]
    # a layer and its submodules ("agents", "agents.transports"), not a namesake ("agentsx")
    loaded = [m for m in _loaded(package, forbidden) if m.split(".")[0] in forbidden]
    assert loaded == [], f"importing {package} loaded: {loaded}"


def _loaded_by_node(prefixes: tuple[str, ...]) -> list[str]:
    """The modules starting with one of ``prefixes`` that ``dyknow node -c FILE`` loads.

    Through the entry point, with a missing config: the node's path imports everything it
    runs before it reads the file, then exits 2.
    """
    return _modules_after(
        "from federation.cli import main\nassert main(['node', '-c', 'no-such-config.toml']) == 2",
        prefixes,
    )


def test_the_node_command_leaves_out_what_only_other_commands_or_peers_use() -> None:
    # a node alone records nothing, serves no Foxglove and has no session to seal (~7 MB of
    # its memory, bench.memory), and its command line is read without typer and the other
    # commands (~2 MB; federation._cli_node); difflib only names near misses in errors;
    # tempfile (with shutil, bz2, lzma: ~0.6 MB) only places the local channel of a node
    # run without $XDG_RUNTIME_DIR
    lazy = (
        "cryptography",
        "difflib",
        "tempfile",
        "dyknow_core._record",
        "federation._foxglove",
        "typer",
        "click",
        "rich",
        "federation._cli_app",
        "federation._cli_reasoning",
        "federation.demo",
    )
    loaded = _loaded_by_node((*lazy, "federation._cli_net"))
    # the node's own modules are there: the entry point did run the node's path
    assert "federation._cli_net" in loaded
    unwanted = [m for m in loaded if any(m == p or m.startswith(p + ".") for p in lazy)]
    assert unwanted == [], f"dyknow node loaded: {unwanted}"
