"""A flight recording from one form into the other (``companion dataset convert SRC DST``): a
folder of our format into one MCAP file (DST ends in ``.mcap``) or back (docs/dataset.md,
"MCAP recordings").

Lossless: the images are copied byte for byte (PNG or JPEG, as recorded), every sample and
published pose with the frame it was fed before, the held flags, the calibration and the
algorithm options; so the converted recording replays to the same poses, bit for bit. Only
flight recordings convert (a dataset in its ingest order); a recording that was never closed
is converted up to its last complete frame and says so in its ``stop_reason``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.drivers.dataset.format import I64, PublishedPose
from companion.drivers.dataset.mcap_writer import McapDatasetWriter
from companion.drivers.dataset.model import Dataset
from companion.drivers.dataset.writer import DatasetWriter
from companion.drivers.safe_files import MAX_IMAGE_BYTES
from companion.errors import DatasetError
from companion.types import CameraFrame, PoseEstimate

CARRIED = ("software", "created", "clock")  # what the converted recording keeps of the meta


@dataclass(frozen=True, slots=True)
class Converted:
    """What a conversion wrote: frames, samples (ranges, attitudes, IMU), published poses."""

    frames: int
    samples: int
    published: int


def encoded_frame(ds: Dataset, index: int) -> bytes:
    """Frame ``index``'s image bytes as stored (PNG or JPEG), not decoded."""
    if ds.image_bytes is not None:
        return ds.image_bytes(index)
    if ds.folder is None or index >= len(ds.frame_names):
        raise DatasetError(f"{ds.path}: frame {index} has no image file")
    return ds.folder.read_bytes(ds.frame_names[index], MAX_IMAGE_BYTES)


def _split(fed: I64 | None, n_samples: int, n_frames: int) -> list[slice]:
    """Per frame, the slice of the samples fed before it (``fed``: their frame indices)."""
    if fed is None or len(fed) != n_samples:
        raise DatasetError("a samples list without the frame each sample was fed before")
    bounds = np.searchsorted(fed, np.arange(n_frames + 1), side="left")
    return [slice(int(bounds[k]), int(bounds[k + 1])) for k in range(n_frames)]


def _pose(p: PublishedPose) -> PoseEstimate:
    return PoseEstimate(
        p.time_us,
        p.position_ned_m,
        p.quat_wxyz,
        p.velocity_ned_m_s,
        np.full((6, 6), np.nan),
        p.reset_counter,
        p.quality_pct,
    )


def _frames(ds: Dataset) -> Iterator[tuple[int, CameraFrame, bool]]:
    held = np.zeros(len(ds), dtype=bool) if ds.frame_held is None else ds.frame_held
    seqs = np.arange(len(ds)) if ds.frame_seqs is None else ds.frame_seqs
    empty = np.zeros((0, 0, 3), dtype=np.uint8)  # the writers take the encoded bytes
    for k in range(len(ds)):
        yield k, CameraFrame(int(ds.frame_times_us[k]), int(seqs[k]), empty), bool(held[k])


def convert_recording(ds: Dataset, dst: Path) -> Converted:
    """Write the recording ``ds`` to ``dst``: an MCAP file when it ends in ``.mcap``, else a
    new folder (FileExistsError / DatasetError when ``dst`` is taken)."""
    if ds.fed_before is None or ds.config is None:
        raise DatasetError(
            f"{ds.path}: not a flight recording (companion run --record): only those convert"
        )
    n = len(ds)
    cut = [
        _split(ds.fed_before[0], len(ds.ranges), n),
        _split(ds.fed_before[1], len(ds.attitudes), n),
        _split(ds.imu_fed if ds.imus else np.zeros(0, dtype=np.int64), len(ds.imus), n),
    ]
    truth = ds.true_range_m if np.isfinite(ds.true_range_m).any() else None
    reason = str(ds.meta.get("stop_reason", ""))
    if not ds.complete:
        reason = reason or f"converted from an unfinished recording ({ds.path})"
    kept: dict[str, Any] = {k: ds.meta[k] for k in CARRIED if k in ds.meta}
    kind = "jpg" if n and encoded_frame(ds, 0)[:2] == b"\xff\xd8" else "png"
    writer: McapDatasetWriter | DatasetWriter
    if dst.suffix == ".mcap":
        image = str(ds.meta.get("image", "colour"))
        writer = McapDatasetWriter(
            dst, ds.config, image=image, image_format=kind, meta={**kept, "converted_from": ds.path}
        )
    else:
        writer = DatasetWriter(dst, ds.config, image_format=kind)
        writer.meta.update(kept)
    poses = sorted(ds.published, key=lambda p: p.time_us)
    p = 0
    for k, frame, held in _frames(ds):
        while p < len(poses) and poses[p].time_us < frame.time_us:  # sent before this frame
            writer.write_pose(_pose(poses[p]))
            p += 1
        r, a, m = (c[k] for c in cut)
        true_m = None if truth is None else [float(x) for x in truth[r]]
        encoded = encoded_frame(ds, k)
        if isinstance(writer, McapDatasetWriter):
            writer.write_frame(
                frame, encoded, ds.ranges[r], ds.attitudes[a], ds.imus[m], held, true_m
            )
        else:
            writer.write_frame(frame, encoded, ds.ranges[r], ds.attitudes[a], ds.imus[m], held)
    for pose in poses[p:]:
        writer.write_pose(_pose(pose))
    writer.close(reason)
    return Converted(n, len(ds.ranges) + len(ds.attitudes) + len(ds.imus), len(poses))
