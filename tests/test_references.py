"""Every ``camloc.x.y`` a docstring, comment or document names in backticks exists: a module moved
or a function renamed leaves no pointer to nowhere behind."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
REFERENCE = re.compile(r"`{1,2}(camloc(?:\.[A-Za-z_][A-Za-z0-9_]*)+)`{1,2}")
SOURCES = ("camloc", "cli", "docs", "benchmarks")


def references() -> list[tuple[str, int, str]]:
    """(file relative to the repository, line, dotted name) of every reference."""
    files = sorted(p for folder in SOURCES for p in (ROOT / folder).rglob("*") if p.suffix in (".py", ".md"))
    found = []
    for path in files + [ROOT / "README.md"]:
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            found += [(str(path.relative_to(ROOT)), number, name) for name in REFERENCE.findall(line)]
    return found


def resolves(name: str) -> bool:
    """Whether the longest importable module prefix of ``name`` has the rest as attributes."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        try:
            target = importlib.import_module(".".join(parts[:k]))
        except ModuleNotFoundError:
            continue
        for attribute in parts[k:]:
            if not hasattr(target, attribute):
                return False
            target = getattr(target, attribute)
        return True
    return False


def test_the_scan_finds_references_and_the_check_rejects_a_wrong_one():
    names = {name for _, _, name in references()}
    assert {"camloc.localize", "camloc.metrics.evaluate", "camloc.kernels.beam.options_for"} <= names
    assert resolves("camloc.beam.BeamSearch")
    assert not resolves("camloc.reference.beam")
    assert not resolves("camloc.beam.NoSuchThing")


def test_every_reference_resolves():
    unresolved = [f"{where}:{line}: `{name}`" for where, line, name in references() if not resolves(name)]
    assert not unresolved, "names that point to nothing in camloc:\n" + "\n".join(unresolved)


LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def test_every_relative_link_of_the_documents_exists():
    documents = sorted(ROOT.glob("*.md")) + sorted(p for folder in SOURCES + ("tests",) for p in (ROOT / folder).rglob("*.md"))
    links = [(path, number, target) for path in documents
             for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
             for target in LINK.findall(line) if "://" not in target and not target.startswith("mailto:")]
    assert len(links) > 20
    broken = [f"{path.relative_to(ROOT)}:{number}: {target}" for path, number, target in links if not (path.parent / target).exists()]
    assert not broken, "links to nothing:\n" + "\n".join(broken)
