"""The flight recorder's writer, as ``[record]`` asks (companion/service/recorder.py): one
MCAP file (``McapDatasetWriter``, the default) or a folder of our format (``DatasetWriter``),
and where it goes (``recording_dir``, ``recording_path``, ``empty_folder_of_ours``).
"""

from __future__ import annotations

import os
import stat
import time
from pathlib import Path
from typing import TYPE_CHECKING, TypeAlias

from companion.config import Config, RecordOptions
from companion.drivers.dataset.writer import DatasetWriter

if TYPE_CHECKING:  # at run time imported on use: a service that records no MCAP never loads it
    from companion.drivers.dataset.mcap_writer import McapDatasetWriter

RecordingWriter: TypeAlias = "DatasetWriter | McapDatasetWriter"


def image_mode(options: RecordOptions, config: Config) -> str:
    """An MCAP recording's images: ``record.image``; auto = grey unless d-Pose (the one stage
    that reads colour: its red marks) is on. A folder's are always colour."""
    if options.format != "mcap":
        return "colour"
    if options.image != "auto":
        return options.image
    return "colour" if config.dpose.enabled else "grey"


def recording_path(wanted: Path, options: RecordOptions, k: int = 1) -> Path:
    """Where a recording of ``record.dir`` (``{start}`` filled in: ``wanted``) goes: the file
    ``wanted.mcap`` or the folder ``wanted``; ``k`` > 1: the k-th sibling (``wanted-k.mcap``,
    ``wanted-k``), when that is taken."""
    if options.format == "mcap":
        from companion.drivers.dataset.mcap_writer import mcap_path  # mcap, zstd: on use

        p = mcap_path(wanted)
        return p if k == 1 else p.with_name(f"{p.stem}-{k}{p.suffix}")
    return wanted if k == 1 else wanted.with_name(f"{wanted.name}-{k}")


def make_writer(
    path: Path, config: Config, options: RecordOptions, software: str, made_for_us: bool = False
) -> RecordingWriter:
    """The writer of a new recording at ``path`` (FileExistsError when anything is there: a
    file, a link, an earlier run's folder). ``made_for_us``: ``path`` is an empty folder we
    own that nobody else may write into (systemd's StateDirectory=), used as it is."""
    o = options
    if o.format == "mcap":
        from companion.drivers.dataset.mcap_writer import McapDatasetWriter

        return McapDatasetWriter(
            path,
            config,
            image=image_mode(o, config),
            image_format=o.image_format,
            png_compression=o.png_compression,
            jpg_quality=o.jpg_quality,
            software=software,
        )
    if not made_for_us:
        path.mkdir(mode=0o755)  # never through a link: EEXIST when one is there
    return DatasetWriter(
        path,
        config,
        image_format=o.image_format,
        png_compression=o.png_compression,
        jpg_quality=o.jpg_quality,
        software=software,
    )


def empty_folder_of_ours(path: Path) -> bool:
    """Whether ``path`` is an empty folder (not a link to one) that we own and nobody else
    may write into: nobody can have planted anything in it, nor can while we record."""
    try:
        st = path.lstat()
    except FileNotFoundError:
        return False
    return (
        stat.S_ISDIR(st.st_mode)
        and st.st_uid == os.geteuid()
        and not st.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
        and not any(path.iterdir())
    )


def recording_dir(template: str, start: time.struct_time | None = None) -> Path:
    """``record.dir`` with ``{start}`` replaced by the start time (local, YYYYmmdd-HHMMSS)."""
    stamp = time.strftime("%Y%m%d-%H%M%S", start or time.localtime())
    return Path(template.replace("{start}", stamp)).expanduser()
