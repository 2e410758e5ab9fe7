"""The repository's rooms, checked (docs/architecture.md; docs/decisions.md, "One installed
package").

Each check reads the source tree as text: an import of the top-level folders by their old names,
a file grown past its room's limit or a history note in place of a date fails here with the file
and line, before a reviewer has to find it.
"""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SOURCE_ROOTS = ("companion", "drivers", "sitl", "tests")


def _python_files(*roots: str) -> list[Path]:
    """Every .py file under ``roots`` (relative to the repository), links not followed twice:
    ``companion/drivers`` and ``companion/sitl`` are links to ``drivers/`` and ``sitl/``."""
    out: list[Path] = []
    for root in roots:
        for path in sorted((REPO / root).rglob("*.py")):
            rel = path.relative_to(REPO)
            if rel.parts[:2] in (("companion", "drivers"), ("companion", "sitl")):
                continue
            out.append(path)
    return out


def test_drivers_and_sitl_are_imported_only_as_companion_subpackages() -> None:
    """``import drivers`` works from the repository's root but not from the wheel, and loads a
    second copy of every module beside ``companion.drivers``: refused."""
    pattern = re.compile(r"^\s*(from|import)\s+(drivers|sitl)\b", re.M)
    found = []
    for path in _python_files(*SOURCE_ROOTS):
        for m in pattern.finditer(path.read_text()):
            line = path.read_text().count("\n", 0, m.start()) + 1
            found.append(f"{path.relative_to(REPO)}:{line}: {m.group(0).strip()}")
    assert found == [], "\n".join(found)


def test_the_links_lead_to_the_top_level_folders() -> None:
    for name in ("drivers", "sitl"):
        link = REPO / "companion" / name
        assert link.is_symlink(), f"companion/{name} must be a link to ../{name}"
        assert link.resolve() == (REPO / name).resolve()


def test_no_history_notes_in_place_of_dates() -> None:
    """The project speaks of the product: when something happened is a date, a commit or an
    issue's title, never a working session's number."""
    pattern = re.compile(r"session\s+[0-9]", re.I)
    found = []
    paths = [*_python_files(*SOURCE_ROOTS)]
    for folder in ("docs", "config", "systemd"):
        paths += sorted(p for p in (REPO / folder).rglob("*") if p.is_file())
    paths += [REPO / n for n in ("README.md", "Makefile", "pyproject.toml")]
    for path in paths:
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            continue  # images
        for i, line in enumerate(text.splitlines(), 1):
            if pattern.search(line) and path.name != "test_layout.py":
                found.append(f"{path.relative_to(REPO)}:{i}")
    assert found == [], "\n".join(found)
