"""Write a real sequence (``import_sources.SourceSequence``) as a dataset of our format
(docs/dataset.md, "Importing real sequences"), with distance sensors synthesised from its depth
images (``import_depth``).

The body is the camera (``T_body_cam`` = identity), so ``groundtruth.txt`` holds the
sequence's camera poses ``T_world_cam`` at the frame stamps and the ``[[rangefinders]]`` mounts
are in the camera frame. ``time_us`` counts from the earliest kept colour or depth stamp
(``time_offset_s`` in meta.toml is that stamp in the source's clock). Each reading is stamped
at its depth image's time; a frame without depth has none. Images are copied byte for byte
(``image_format = "keep"``) or re-encoded as PNG / JPEG (quality 95).
"""

from __future__ import annotations

import datetime
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion import __version__
from companion.config import Config, MountConfig, RangefinderConfig, to_dict
from companion.drivers.dataset.format import FORMAT_NAME, FORMAT_VERSION, RANGE_COLUMNS
from companion.drivers.dataset.import_depth import (
    BeamMiss,
    beam_in_camera,
    march_beam,
    noisy_reading,
)
from companion.drivers.dataset.import_sources import SourceSequence
from companion.drivers.dataset.toml_text import toml_dumps
from companion.drivers.dataset.tum import write_tum
from companion.drivers.safe_files import MAX_IMAGE_BYTES, SafeFolder
from companion.errors import DatasetError

IMAGE_FORMATS = ("keep", "png", "jpg")
RANGES_SOURCE = "synthesised from depth images"


def _beam(sensor_id: int, x_m: float, y_m: float, tilt_deg: float) -> RangefinderConfig:
    """A sensor ``(x_m, y_m)`` off the lens in the camera plane (z = 0), its beam tilted
    ``tilt_deg`` away from the optical axis towards its own side (ZYX roll/pitch of the mount,
    as ``companion.config._outward``)."""
    r = float(np.hypot(x_m, y_m))
    return RangefinderConfig(
        sensor_id=sensor_id,
        mount=MountConfig(
            xyz_m=(x_m, y_m, 0.0),
            rpy_deg=(round(-tilt_deg * y_m / r, 3), round(tilt_deg * x_m / r, 3), 0.0),
        ),
        min_m=0.1,
        max_m=12.0,
        sigma_a_m=0.01,
    )


# Four beams near the optical axis, a few cm off the lens, tilted 6-12 deg outward in an
# asymmetric pattern: at 1 m they land 10-21 cm from the axis (60-110 px at f = 520 px).
DEFAULT_BEAMS: tuple[RangefinderConfig, ...] = (
    _beam(0, 0.05, 0.01, 6.0),
    _beam(1, -0.02, 0.045, 9.0),
    _beam(2, -0.045, -0.02, 12.0),
    _beam(3, 0.015, -0.05, 8.0),
)


@dataclass(slots=True)
class ImportSummary:
    """What an import wrote: frames, readings, and what it left out (by reason)."""

    frames: int = 0
    readings: int = 0
    path_length_m: float = 0.0
    dropped: dict[str, int] = field(default_factory=dict)


def _depth_image(folder: SafeFolder, name: str, per_m: float, size: tuple[int, int]) -> Any:
    """A 16-bit depth PNG in metres (H, W); DatasetError naming the file when it is not one of
    the colour image's size."""
    data = folder.read_bytes(name, MAX_IMAGE_BYTES)
    raw = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16 or raw.shape != (size[1], size[0]):
        shape = None if raw is None else (raw.shape, str(raw.dtype))
        raise DatasetError(
            f"{folder.shown}/{name}: not a {size[0]}x{size[1]} 16-bit depth PNG (got {shape})"
        )
    depth = raw.astype(np.float64) / per_m
    depth[raw == 65535] = 0.0  # 7-Scenes' "no depth"
    return depth


def _image_bytes(
    folder: SafeFolder, name: str, image_format: str, jpg_quality: int = 95
) -> tuple[bytes, str]:
    """The image file's bytes and extension: the source's (keep) or re-encoded."""
    data = folder.read_bytes(name, MAX_IMAGE_BYTES)
    ext = Path(name).suffix.lower().lstrip(".").replace("jpeg", "jpg")
    if image_format == "keep":
        if ext not in ("png", "jpg"):
            raise DatasetError(f"{folder.shown}/{name}: keep needs a PNG or JPEG source")
        return data, ext
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"{folder.shown}/{name}: the image does not decode")
    params = [cv2.IMWRITE_JPEG_QUALITY, jpg_quality] if image_format == "jpg" else []
    ok, buf = cv2.imencode(f".{image_format}", img, params)
    if not ok:
        raise DatasetError(f"{folder.shown}/{name}: cannot encode as {image_format}")
    return bytes(buf), image_format


def select_frames(seq: SourceSequence, frames: str) -> SourceSequence:
    """``A:B`` (Python slice of the kept frames, either side optional) of the sequence."""
    if not frames:
        return seq
    parts = frames.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        a = int(parts[0]) if parts[0] else None
        b = int(parts[1]) if parts[1] else None
    except ValueError:
        raise DatasetError(f"--frames: A:B (frame indexes), got {frames!r}") from None
    chosen = seq.frames[a:b]
    if not chosen:
        raise DatasetError(f"--frames {frames}: no frame of the {len(seq.frames)} kept")
    return SourceSequence(
        seq.format, seq.camera, seq.depth_per_m, chosen, seq.camera_note, dict(seq.dropped)
    )


def import_sequence(
    seq: SourceSequence,
    src: SafeFolder,
    out: Path,
    rangefinders: Sequence[RangefinderConfig] = DEFAULT_BEAMS,
    *,
    seed: int = 1,
    image_format: str = "keep",
    jpg_quality: int = 95,
    source_meta: dict[str, Any] | None = None,
) -> ImportSummary:
    """Write ``seq`` (its files in ``src``) into the new folder ``out`` in our format; the
    readings of ``rangefinders`` from the depth images (none without depth), noise seeded by
    ``seed``; images kept or re-encoded (``image_format``, ``jpg_quality`` 1..100).
    ``source_meta``: more keys for meta.toml (where the sequence came from)."""
    if image_format not in IMAGE_FORMATS:
        raise DatasetError(f"--image-format: one of {', '.join(IMAGE_FORMATS)}")
    if not 1 <= jpg_quality <= 100:
        raise DatasetError(f"--jpg-quality: 1..100, got {jpg_quality}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise DatasetError(f"{out} exists and is not an empty folder")
    sensors = list(rangefinders) if seq.depth_per_m > 0 else []
    ids = [r.sensor_id for r in sensors]
    if len(set(ids)) != len(ids):
        raise DatasetError(f"rangefinders: sensor ids repeat: {ids}")
    (out / "images").mkdir(parents=True, exist_ok=True)
    cam = seq.camera
    model, size = cam.model(), (cam.width, cam.height)
    t0 = min(min(f.time_s, f.depth_time_s) for f in seq.frames)
    summary = ImportSummary(dropped=dict(seq.dropped))
    for reason in ("no_surface", "missing_depth", "depth_edge"):
        summary.dropped[f"beam_{reason}"] = 0
    rng = np.random.default_rng(seed)
    frame_rows, range_rows = ["time_us,seq,filename"], []
    for k, f in enumerate(seq.frames):
        data, ext = _image_bytes(src, f.image, image_format, jpg_quality)
        name = f"images/{k:06d}.{ext}"
        (out / name).write_bytes(data)
        frame_rows.append(f"{round((f.time_s - t0) * 1e6)},{k},{name}")
        if f.depth is None or not sensors:
            continue
        depth = _depth_image(src, f.depth, seq.depth_per_m, size)
        t_us = round((f.depth_time_s - t0) * 1e6)
        for rf in sensors:
            hit = march_beam(depth, model, *beam_in_camera(rf))
            if isinstance(hit, BeamMiss):
                summary.dropped[f"beam_{hit.reason}"] += 1
                continue
            r = noisy_reading(rf, hit.range_m, rng)
            range_rows.append(
                (
                    t_us,
                    rf.sensor_id,
                    f"{t_us},{rf.sensor_id},{r.distance_m!r},{rf.min_m!r},"
                    f"{rf.max_m!r},{r.signal_quality},{r.true_distance_m!r}",
                )
            )
    range_rows.sort(key=lambda row: (row[0], row[1]))
    (out / "frames.csv").write_text("\n".join(frame_rows) + "\n")
    header = ",".join([*RANGE_COLUMNS, "true_distance_m"])
    (out / "ranges.csv").write_text("\n".join([header, *(row for *_, row in range_rows)]) + "\n")
    times = np.array([f.time_s - t0 for f in seq.frames])
    poses = np.stack([f.T_world_cam for f in seq.frames])
    write_tum(out / "groundtruth.txt", times, poses)
    summary.frames = len(seq.frames)
    summary.readings = len(range_rows)
    summary.path_length_m = float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())
    shown = f"jpg (quality {jpg_quality})" if image_format == "jpg" else image_format
    _write_tomls(out, seq, sensors, summary, t0, seed, shown, source_meta or {})
    return summary


def _write_tomls(
    out: Path,
    seq: SourceSequence,
    sensors: list[RangefinderConfig],
    summary: ImportSummary,
    t0: float,
    seed: int,
    image_format: str,
    source_meta: dict[str, Any],
) -> None:
    config = Config(camera=seq.camera, rangefinders=tuple(sensors))
    mounts = {f"T_body_rf{r.sensor_id}": r.mount.T_body_sensor().tolist() for r in sensors}
    calib = {
        "camera": to_dict(config.camera),
        "rangefinders": to_dict(config.rangefinders),
        "matrices": {"T_body_cam": config.camera.T_body_cam().tolist(), **mounts},
    }
    meta: dict[str, Any] = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "software": __version__,
        "source": "import",
        "importer": seq.format,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "world": "none",
        "frames": summary.frames,
        "path_length_m": summary.path_length_m,
        "camera": seq.camera_note,
        "body": "the camera (T_body_cam = identity); groundtruth.txt: the sequence's camera "
        "poses in its own world (not NED)",
        "time_offset_s": t0,
        "image_format": image_format,
        "rangefinders_source": RANGES_SOURCE if sensors else "none",
        "seed": seed,
        "readings": summary.readings,
        "dropped": dict(summary.dropped),
        **source_meta,
    }
    (out / "meta.toml").write_text(toml_dumps(meta))
    (out / "calibration.toml").write_text(
        "# Camera intrinsics/distortion and the synthesised sensors' mounts (body = camera),\n"
        "# in companion's config schema; [matrices] repeats them as 4x4 T_body_sensor.\n"
        + toml_dumps(calib)
    )
