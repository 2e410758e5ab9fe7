"""Open a dataset: a folder of ours (meta.toml) or EuRoC's (mav0/cam0), told apart by its
files, or an MCAP recording of ours (a file)."""

from __future__ import annotations

from pathlib import Path

from companion.drivers.dataset.euroc import read_euroc
from companion.drivers.dataset.format import FORMAT_NAME
from companion.drivers.dataset.model import Dataset
from companion.drivers.dataset.ours import read_ours
from companion.drivers.safe_files import (
    SafeFolder,
)
from companion.errors import DatasetError


def open_dataset(path: str | Path) -> Dataset:
    """Open a dataset folder of our format or EuRoC's (detected by its files), read under
    the discipline of drivers/safe_files.py, or an MCAP recording of ours (a ``.mcap`` file,
    or any file that is not a folder: drivers/dataset/mcap_reader.py): DatasetError naming
    the file, the row and the field for anything it cannot take; rows of samples that do not
    parse are left out and counted (``Dataset.skipped``)."""
    p = Path(path)
    if p.suffix == ".mcap" or (p.exists() and not p.is_dir()):
        from companion.drivers.dataset.mcap_reader import read_mcap  # mcap, zstd: on use

        return read_mcap(p)
    if not p.is_dir():
        raise DatasetError(f"dataset folder not found: {p}")
    folder = SafeFolder(p)
    if folder.exists("meta.toml"):
        return read_ours(folder)
    if folder.exists("mav0/cam0") or folder.exists("cam0/data.csv"):
        return read_euroc(folder)
    raise DatasetError(f"{p}: neither a {FORMAT_NAME} folder (meta.toml) nor EuRoC (mav0/cam0)")
