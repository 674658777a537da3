"""The docs and benchmarks cite nothing a clone of the repository does not have."""

import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# Directories a clone does not have or that are not ours (installed, generated, cached).
SKIP = {".git", ".venv", "node_modules", "__pycache__", "build", "dist", "out", "artifacts"}
SKIP |= {".mypy_cache", ".ruff_cache", ".pytest_cache", ".hypothesis"}

# A relative path that climbs: ``../x/y.md``, in backticks or bare.
CLIMB = re.compile(r"(?<![\w.])((?:\.\./)+[^\s`'\"()\[\]<>,;]*(?:<[\w-]+>[^\s`'\"()\[\]<>,;]*)*)")
# A markdown link or image target: ``[text](target)``.
LINK = re.compile(r"\]\(([^)\s]+)\)")
# A path into somebody's machine rather than the repository.
MACHINE = re.compile(r"(?<![\w./-])(?:/work/|/home/|/Users/|/root/|~/)[^\s`'\"()\[\]<>,;]*")
# A cited Markdown file: ``docs/wire.md``, ``shared/ANCHORS.md``.
MD_FILE = re.compile(r"(?<![\w./-])((?:\.\./)*[\w-]+(?:/[\w.-]+)*/[\w.-]+\.md)\b")


def _walk(top: Path) -> list[Path]:
    """Every file under ``top``, never descending into ``SKIP``."""
    files: list[Path] = []
    for dirpath, dirnames, filenames in os.walk(top):
        dirnames[:] = sorted(d for d in dirnames if d not in SKIP)
        files.extend(Path(dirpath, f) for f in filenames)
    return files


def _cited_files() -> list[Path]:
    """Every Markdown file of the tree, every text file under docs/, and the benchmarks."""
    found = []
    for path in _walk(ROOT):
        wanted = {"docs": {".md", ".txt"}, "bench": {".py"}}.get(path.relative_to(ROOT).parts[0])
        if path.suffix == ".md" or (wanted and path.suffix in wanted):
            found.append(path)
    return sorted(found)


def _inside(base: Path, target: str) -> bool:
    """Whether ``target``, relative to ``base``, names something the repository holds.

    Placeholders (``<platform>``) match any name. A generated directory (keys made by a
    script, ignored by git) counts when its parent, below the root, is in the repository.
    """
    pattern = re.sub(r"<[\w-]+>", "*", target.rstrip("/.:"))
    if "*" in pattern:
        return any(p.resolve().is_relative_to(ROOT) for p in base.glob(pattern))
    resolved = (base / pattern).resolve()
    if not resolved.is_relative_to(ROOT):
        return False
    return resolved.exists() or (resolved.parent.exists() and resolved.parent != ROOT)


def _outside(text: str, here: Path) -> list[str]:
    """The paths ``text`` (a file in ``here``) cites outside the repository or missing."""
    bad: dict[str, int] = {}  # each cited path once, at its first place in the text
    for m in CLIMB.finditer(text):
        target = m.group(1)
        if not target.strip("./") or _inside(here, target):
            continue
        # a README may describe files below it with paths relative to those files
        below = {f.parent for f in _walk(here)}
        if not any(_inside(d, target) for d in below):
            bad.setdefault(target, m.start(1))
    for m in LINK.finditer(text):
        target = m.group(1).split("#")[0]
        if target and not re.match(r"[a-z]+:", target) and not _inside(here, target):
            bad.setdefault(target, m.start(1))
    for m in MACHINE.finditer(text):
        bad.setdefault(m.group(0), m.start())
    for m in MD_FILE.finditer(text):
        cited = m.group(1)
        if not (_inside(here, cited) or _inside(ROOT, cited)):
            bad.setdefault(cited, m.start(1))
    return sorted(bad, key=bad.__getitem__)


def test_docs_and_benchmarks_cite_only_paths_inside_the_repository() -> None:
    files = _cited_files()
    assert {"docs", "bench"} <= {f.parent.name for f in files}
    bad = {}
    for f in files:
        if cited := _outside(f.read_text(encoding="utf-8", errors="replace"), f.parent):
            bad[str(f.relative_to(ROOT))] = cited
    assert bad == {}, f"cite the source (docs/references.md), not a file a clone lacks: {bad}"


def test_the_check_sees_a_path_outside_the_repository() -> None:
    text = (
        "See `../shared/DYKNOW.md` section 2, [x](../../elsewhere.md), /work/shared/x.md,\n"
        "`shared/ANCHORS.md`; fine: `docs/wire.md`, [y](core.md), `../README.md`.\n"
    )
    assert _outside(text, ROOT / "docs") == [
        "../shared/DYKNOW.md",
        "../../elsewhere.md",
        "/work/shared/x.md",
        "shared/ANCHORS.md",
    ]
