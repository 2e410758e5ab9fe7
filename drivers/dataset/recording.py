"""The flight recorder's writer, as ``[record]`` asks (companion/service/recorder.py): one
MCAP file (``McapDatasetWriter``, the default) or a folder of our format (``DatasetWriter``).
"""

from __future__ import annotations

from pathlib import Path

from companion.config import Config, RecordOptions
from companion.drivers.dataset.mcap_writer import McapDatasetWriter, mcap_path
from companion.drivers.dataset.writer import DatasetWriter

RecordingWriter = DatasetWriter | McapDatasetWriter


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
