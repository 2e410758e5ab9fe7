"""The manifest of the real sequences the project uses (``config/real_sequences.toml``) and
their rebuild from git snapshots (``companion dataset rebuild``).

An entry (``[[sequence]]``) names where the raw files are (``repository`` owner/name,
``revision`` the git commit, ``path`` in it, ``include`` the files and folders under ``path``
the importer reads), the ``licence``, whether the sequence may be committed (``commit``), the
``importer`` (one of ``IMPORTERS``: a format of ``import_sources.FORMATS``, or ``rislab``)
with its ``args`` (``camera``, ``sequence``, ``frames``, ``seed``, ``image_format``,
``jpg_quality``; ``focal_px``, ``k1``, ``k2`` for rislab) and the checksums:
``sha256``, the SHA-256 of every file keyed by its path under ``path``, or (for thousands of files)
``tree_sha256``, the SHA-256 of the sorted lines "path sha256\n" of them all. A rebuild
extracts those files from the snapshot (``git --git-dir SNAPSHOT archive REVISION``), checks
the checksums (a missing, changed or unlisted file is an error naming it; a ``tree_sha256``
mismatch names the entry) and runs the importer.
"""

from __future__ import annotations

import hashlib
import io
import subprocess
import tarfile
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion.config import RangefinderConfig
from companion.drivers.dataset.import_sources import FORMATS, read_source
from companion.drivers.dataset.import_write import (
    DEFAULT_BEAMS,
    ImportSummary,
    import_sequence,
    select_frames,
)
from companion.drivers.safe_files import SafeFolder
from companion.errors import ConfigError, DatasetError
from companion.toml_files import read_toml

# every importer a manifest entry (or `companion dataset import`) may name
IMPORTERS = (*FORMATS, "rislab")
ARG_KEYS = (
    "camera",
    "sequence",
    "frames",
    "seed",
    "image_format",
    "jpg_quality",
    "focal_px",
    "k1",
    "k2",
)
_STR_KEYS = ("name", "repository", "revision", "path", "licence", "importer")


@dataclass(frozen=True, slots=True)
class RealSequence:
    """One manifest entry (see the module)."""

    name: str
    repository: str
    revision: str
    path: str
    licence: str
    commit: bool
    importer: str
    include: tuple[str, ...] = ()
    args: dict[str, Any] = field(default_factory=dict)
    sha256: dict[str, str] = field(default_factory=dict)
    tree_sha256: str = ""

    def under(self, name: str = "") -> str:
        """``name`` under the entry's ``path`` in the repository (``path`` "." = its root)."""
        parts = [p for p in (self.path.strip("/"), name) if p and p != "."]
        return "/".join(parts) or "."


def _entry(raw: Any, index: int) -> RealSequence:
    where = f"sequence[{index}]"
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: a table expected")
    unknown = sorted(set(raw) - {*_STR_KEYS, "commit", "include", "args", "sha256", "tree_sha256"})
    if unknown:
        raise ConfigError(f"{where}.{unknown[0]}: unknown key")
    for key in _STR_KEYS:
        if not isinstance(raw.get(key), str) or not raw[key]:
            raise ConfigError(f"{where}.{key}: a non-empty string expected")
    if not isinstance(raw.get("commit"), bool):
        raise ConfigError(f"{where}.commit: true or false (may it be committed?)")
    include = raw.get("include", [])
    if not isinstance(include, list) or not all(isinstance(x, str) for x in include):
        raise ConfigError(f"{where}.include: a list of paths expected")
    args = raw.get("args", {})
    if not isinstance(args, dict) or set(args) - set(ARG_KEYS):
        raise ConfigError(f"{where}.args: a table of {', '.join(ARG_KEYS)}")
    sums = raw.get("sha256", {})
    if not isinstance(sums, dict) or not all(
        isinstance(v, str) and len(v) == 64 for v in sums.values()
    ):
        raise ConfigError(f"{where}.sha256: a table of path = 64 hex digits")
    tree = raw.get("tree_sha256", "")
    if not isinstance(tree, str) or len(tree) not in (0, 64) or not (sums or tree):
        raise ConfigError(f"{where}.tree_sha256: 64 hex digits (or a sha256 table)")
    return RealSequence(
        raw["name"],
        raw["repository"],
        raw["revision"],
        raw["path"],
        raw["licence"],
        raw["commit"],
        raw["importer"],
        tuple(include),
        dict(args),
        dict(sums),
        tree,
    )


def read_manifest(path: Path) -> list[RealSequence]:
    """The entries of the manifest at ``path``; ConfigError naming the key for a bad one."""
    data = read_toml(path)
    entries = data.get("sequence", [])
    if not isinstance(entries, list):
        raise ConfigError(f"{path}: sequence: an array of tables ([[sequence]]) expected")
    out = [_entry(raw, i) for i, raw in enumerate(entries)]
    names = [e.name for e in out]
    if len(set(names)) != len(names):
        raise ConfigError(f"{path}: sequence names repeat: {names}")
    return out


def file_checksums(root: Path, include: tuple[str, ...] = ()) -> dict[str, str]:
    """SHA-256 (hex) of every regular file under ``root`` (or under its ``include`` entries),
    keyed by the path relative to ``root``, sorted."""
    tops = [root / p for p in include] if include else [root]
    files = sorted(
        f for top in tops for f in ([top] if top.is_file() else top.rglob("*")) if f.is_file()
    )
    return {
        f.relative_to(root).as_posix(): hashlib.sha256(f.read_bytes()).hexdigest() for f in files
    }


def snapshot_dir(snapshots: Path, repository: str) -> Path:
    """The git directory of ``owner/name`` under ``snapshots``: ``owner+name/repo`` (bare) or
    its ``.git``, else ``owner+name`` itself."""
    base = snapshots / repository.replace("/", "+")
    for candidate in (base / "repo" / ".git", base / "repo"):
        if candidate.exists():
            return candidate
    return base


def extract(entry: RealSequence, snapshots: Path, dest: Path) -> Path:
    """Extract the entry's files from its git snapshot into ``dest``; the folder of ``path``.
    DatasetError naming the snapshot or the revision when git cannot give them."""
    git_dir = snapshot_dir(snapshots, entry.repository)
    if not git_dir.exists():
        raise DatasetError(f"{entry.name}: no snapshot of {entry.repository} at {git_dir}")
    paths = [entry.under(p) for p in entry.include] or [entry.under()]
    cmd = [
        "git",
        "--git-dir",
        str(git_dir),
        "archive",
        "--format=tar",
        entry.revision,
        "--",
        *paths,
    ]
    done = subprocess.run(cmd, capture_output=True, check=False)
    if done.returncode != 0:
        err = done.stderr.decode(errors="replace").strip().splitlines()[-1:]
        raise DatasetError(f"{entry.name}: git archive {entry.revision[:12]} of {git_dir}: {err}")
    with tarfile.open(fileobj=io.BytesIO(done.stdout)) as tar:
        tar.extractall(dest, filter="data")
    return dest / entry.under()


def tree_checksum(sums: dict[str, str]) -> str:
    """SHA-256 (hex) of the sorted lines "path sha256\\n" of ``sums``."""
    text = "".join(f"{name} {digest}\n" for name, digest in sorted(sums.items()))
    return hashlib.sha256(text.encode()).hexdigest()


def check_checksums(entry: RealSequence, root: Path) -> None:
    """DatasetError naming the first file that is missing, changed, or not in the manifest
    (or the entry, when its ``tree_sha256`` differs)."""
    got = file_checksums(root, entry.include)
    if entry.tree_sha256:
        tree = tree_checksum(got)
        if tree != entry.tree_sha256:
            raise DatasetError(
                f"{entry.name}: the {len(got)} files' tree_sha256 {tree[:16]}... is not the "
                f"manifest's {entry.tree_sha256[:16]}..."
            )
        if not entry.sha256:
            return
    for name, want in sorted(entry.sha256.items()):
        if name not in got:
            raise DatasetError(f"{entry.name}: {name} is missing from the snapshot")
        if got[name] != want:
            raise DatasetError(
                f"{entry.name}: {name}: sha256 {got[name][:16]}... is not the manifest's "
                f"{want[:16]}..."
            )
    extra = sorted(set(got) - set(entry.sha256))
    if extra:
        raise DatasetError(f"{entry.name}: {extra[0]} is not in the manifest (no checksum)")


def run_importer(
    entry: RealSequence,
    src: Path,
    out: Path,
    rangefinders: tuple[RangefinderConfig, ...] = DEFAULT_BEAMS,
) -> ImportSummary:
    """The entry's importer on the folder ``src`` into ``out``."""
    a = entry.args
    if entry.importer == "rislab":
        from companion.config import load_config
        from companion.drivers.dataset.rislab import import_rislab

        k1, k2 = float(a.get("k1", 0.0)), float(a.get("k2", 0.0))
        first, _, last = str(a.get("frames", "")).partition(":")
        return import_rislab(
            src,
            out,
            load_config(),
            focal_px=float(a.get("focal_px", 235.5)),
            dist=(k1, k2, 0.0, 0.0, 0.0),
            frames=(int(first), int(last)) if last else None,
            seed=int(a.get("seed", 1)),
        )
    if entry.importer not in FORMATS:
        raise DatasetError(
            f"{entry.name}: importer {entry.importer!r} is not built here (this importer knows "
            f"{', '.join(IMPORTERS)})"
        )
    folder = SafeFolder(src)
    seq = read_source(
        entry.importer, folder, str(a.get("camera", "fr1")), str(a.get("sequence", ""))
    )
    seq = select_frames(seq, str(a.get("frames", "")))
    return import_sequence(
        seq,
        folder,
        out,
        rangefinders,
        seed=int(a.get("seed", 1)),
        image_format=str(a.get("image_format", "keep")),
        jpg_quality=int(a.get("jpg_quality", 95)),
        source_meta={
            "source_repository": entry.repository,
            "source_revision": entry.revision,
            "source_path": entry.path,
            "licence": entry.licence,
            "sequence": entry.name,
        },
    )


def rebuild(entry: RealSequence, snapshots: Path, out: Path) -> ImportSummary:
    """Extract the entry from its snapshot, check its checksums, import it into ``out``."""
    if entry.importer not in IMPORTERS:
        run_importer(entry, Path("."), out)  # raises: not built here
    with tempfile.TemporaryDirectory(prefix=f"rebuild-{entry.name}-") as tmp:
        root = extract(entry, snapshots, Path(tmp))
        check_checksums(entry, root)
        return run_importer(entry, root, out)
