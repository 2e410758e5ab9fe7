"""The repository's rooms, checked (docs/architecture.md; docs/decisions.md, "One installed
package").

Each check reads the source tree as text: an import of the top-level folders by their old names,
a file grown past its room's limit or a history note in place of a date fails here with the file
and line, before a reviewer has to find it.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

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


TOP_LEVEL = {  # what the README's "Layout" lists, and the repository's own files
    *(".ci", ".gitignore", "LICENSE", "MANIFEST.in", "Makefile", "README.md", "pyproject.toml"),
    *("companion", "config", "docs", "drivers", "sitl", "systemd", "tests"),
}


def test_the_top_level_holds_the_product_only() -> None:
    """What git tracks at the repository's top level is the product's layout (README.md,
    "Layout"); a run's output saved in the working folder and committed by mistake (an
    array of poses, a log) fails here."""
    if not (REPO / ".git").exists():
        pytest.skip("not a git checkout: nothing says which files are tracked")
    listed = subprocess.run(
        ["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout.splitlines()
    extra = sorted({name.split("/")[0] for name in listed} - TOP_LEVEL)
    assert extra == [], f"tracked at the top level, not part of the layout: {extra}"


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


def _lines(path: Path) -> int:
    return len(path.read_text().splitlines())


def _product_files() -> list[Path]:
    return _python_files("companion", "drivers", "sitl")


def test_no_room_holds_an_oversized_file() -> None:
    """A file past its room's limit is a room that needs another door: 600 lines for product
    code (the numba kernels aside: one kernel per function, compiled together), 350 for the
    service's parts and the pipeline's stages, 500 for a test file."""
    over = []
    for path in _product_files():
        rel = path.relative_to(REPO)
        limit = (
            350 if rel.parts[:2] in (("companion", "service"), ("companion", "pipeline")) else 600
        )
        if path.name == "_kernels.py":
            continue
        if _lines(path) > limit:
            over.append(f"{rel}: {_lines(path)} lines (limit {limit})")
    for path in _python_files("tests"):
        if _lines(path) > 500:
            over.append(f"{path.relative_to(REPO)}: {_lines(path)} lines (limit 500)")
    assert over == [], "\n".join(over)


# Product modules whose tests live elsewhere than their mirrored folder: the test file, and what
# in it shows that it still exercises the module (a cover that no longer does fails below).
COVERED_ELSEWHERE = {
    "companion.errors": ("tests/companion/config/test_config.py", "ConfigError"),
    "companion.offline": ("tests/e2e/test_robustness.py", "from companion.offline import"),
    "companion.options": ("tests/companion/config/test_config.py", "camera.fx: must be > 0"),
    "companion.redact": ("tests/e2e/test_secrets_and_disks.py", "from companion.redact import"),
    "companion.reporting": ("tests/companion/evaluation/test_evaluation.py", "report.md"),
    "companion.service_options": (
        "tests/companion/service/test_mqtt.py",
        "from companion.service_options import",
    ),
    "companion.types": ("tests/companion/pipeline/test_pipeline.py", "from companion.types import"),
    # the TOML reader through the config loader's tests (size, bytes, nesting, syntax)
    "companion.toml_files": (
        "tests/companion/config/test_config.py",
        "from companion.toml_files import",
    ),
    # the laser and board maths through `companion calibrate` and its files
    "companion.calibration_maths": (
        "tests/companion/calibration/test_calibration.py",
        "from companion.calibration_maths",
    ),
    "companion.calibration_maths.board": (
        "tests/companion/calibration/test_calibration.py",
        "from companion.calibration_maths.board import",
    ),
    "companion.calibration_maths.intrinsics": (
        "tests/companion/calibration/test_calibration.py",
        "from companion.calibration_maths.intrinsics import",
    ),
    "companion.calibration_maths.lasers": (
        "tests/companion/calibration/test_calibration.py",
        "from companion.calibration_maths.lasers import",
    ),
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = list(rel.parts)
    if parts[0] in ("drivers", "sitl"):
        parts.insert(0, "companion")
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _mirror(path: Path) -> Path:
    """The tests/ folder of a product file: its package's folder under tests/ (drivers/x.py ->
    tests/drivers, sitl/world/render.py -> tests/sitl/world, companion/vo/ba.py ->
    tests/companion/vo); a module directly in companion/ is a room of its own
    (companion/config.py -> tests/companion/config)."""
    rel = path.relative_to(REPO)
    folder = rel.parent if path.name == "__init__.py" or rel.parent != Path("companion") else None
    if folder is None:
        folder = rel.parent / path.stem
    return REPO / "tests" / folder


def test_every_product_module_has_its_test_folder_or_a_named_cover() -> None:
    missing = []
    for path in _product_files():
        module = _module_name(path)
        if module in ("companion", "companion.drivers", "companion.sitl") or path.name in (
            "__main__.py",
        ):
            continue
        if module in COVERED_ELSEWHERE:
            cover, evidence = COVERED_ELSEWHERE[module]
            text = (REPO / cover).read_text() if (REPO / cover).exists() else ""
            if evidence not in text:
                missing.append(f"{module}: its named cover {cover} lacks {evidence!r}")
            continue
        folder = _mirror(path)
        if not any(folder.glob("test_*.py")):
            missing.append(f"{module}: no tests in {folder.relative_to(REPO)}/")
    assert missing == [], "\n".join(missing)


def test_the_docs_name_files_that_exist() -> None:
    """A path in a page a user reads (README, docs/ but the dated history in decisions.md) is a
    file or folder of this repository: a room that moved takes its mentions with it."""
    pattern = re.compile(
        r"(?<![\w/.-])((?:companion|drivers|sitl|tests|config|systemd|docs)/[\w./-]*\w)"
    )
    missing = []
    pages = [REPO / "README.md", REPO / "Makefile", *sorted((REPO / "docs").glob("*.md"))]
    for page in pages:
        if page.name == "decisions.md":
            continue
        for m in pattern.finditer(page.read_text()):
            if not (REPO / m.group(1)).exists():
                missing.append(f"{page.relative_to(REPO)}: {m.group(1)}")
    assert missing == [], "\n".join(sorted(set(missing)))
