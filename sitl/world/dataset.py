"""Record datasets of our own format (docs/dataset.md) from the simulator, and contact sheets.

Reading (ours and EuRoC) is ``drivers.dataset``: a recording is read the same way whether the
simulator or a real vehicle made it.
"""

from __future__ import annotations

import csv
import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import tomli_w

from companion import __version__
from companion.config import Config, to_dict
from companion.drivers.dataset import FORMAT_NAME, FORMAT_VERSION, Dataset, write_tum
from companion.errors import DatasetError
from companion.types import F64

if TYPE_CHECKING:
    from companion.sitl.world.scenario import Scenario, Step

# ----------------------------------------------------------------------------- recording


_RANGE_COLUMNS = [
    "time_us",
    "sensor_id",
    "distance_m",
    "min_m",
    "max_m",
    "signal_quality",
    "true_distance_m",
]
_ATTITUDE_COLUMNS = ["time_us", "qw", "qx", "qy", "qz", "wx_rad_s", "wy_rad_s", "wz_rad_s"]


def record(
    cfg: Config,
    out: str | Path,
    *,
    image_format: str = "jpg",
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Fly the SITL scenario of ``cfg.sitl`` and write a dataset folder; returns its path."""
    from companion.sitl.world.scenario import Scenario

    out_dir = _prepare_folder(Path(out), image_format, overwrite)
    scenario = Scenario(cfg)
    gt_times, gt_poses = _write_flight(scenario, out_dir, image_format, progress)
    write_tum(out_dir / "groundtruth.txt", np.asarray(gt_times), np.asarray(gt_poses))
    _write_calibration(cfg, out_dir)
    _write_meta(cfg, scenario, out_dir)
    return out_dir


def _prepare_folder(out_dir: Path, image_format: str, overwrite: bool) -> Path:
    """An empty dataset folder with its images/ (an existing one only with ``overwrite``)."""
    if out_dir.exists():
        if not overwrite and any(out_dir.iterdir()):
            raise DatasetError(f"{out_dir} exists and is not empty (use --overwrite)")
        shutil.rmtree(out_dir)
    if image_format not in ("jpg", "png"):
        raise DatasetError(f"image format must be jpg or png, got {image_format!r}")
    (out_dir / "images").mkdir(parents=True)
    return out_dir


def _write_flight(
    scenario: Scenario, out_dir: Path, image_format: str, progress: bool
) -> tuple[list[float], list[F64]]:
    """Fly the scenario: frames.csv, ranges.csv, attitude.csv and the images; the truth back."""
    from tqdm import tqdm

    from companion.sitl.world.scenario import render_threads

    enc = (
        [cv2.IMWRITE_JPEG_QUALITY, 95]
        if image_format == "jpg"
        else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    )
    gt_times: list[float] = []
    gt_poses: list[F64] = []
    with (
        (out_dir / "frames.csv").open("w", newline="") as f_frames,
        (out_dir / "ranges.csv").open("w", newline="") as f_ranges,
        (out_dir / "attitude.csv").open("w", newline="") as f_att,
    ):
        w_frames = csv.writer(f_frames)
        w_ranges = csv.writer(f_ranges)
        w_att = csv.writer(f_att)
        w_frames.writerow(["time_us", "seq", "filename"])
        w_ranges.writerow(_RANGE_COLUMNS)
        w_att.writerow(_ATTITUDE_COLUMNS)
        bar = tqdm(
            total=scenario.n_frames,
            unit="frame",
            desc=f"recording {out_dir.name}",
            file=sys.stderr,
            disable=not progress,
            dynamic_ncols=True,
        )
        for step in scenario.steps(workers=render_threads()):  # rendered ahead, in order
            _write_sensors(step, w_att, w_ranges)
            name = f"images/{step.frame.seq:06d}.{image_format}"
            if not cv2.imwrite(str(out_dir / name), step.frame.image_bgr, enc):
                raise DatasetError(f"cannot write {out_dir / name}")
            w_frames.writerow([step.frame.time_us, step.frame.seq, name])
            gt_times.append(step.frame.time_us * 1e-6)
            gt_poses.append(step.T_world_body)
            bar.update(1)
        bar.close()
    return gt_times, gt_poses


def _write_sensors(step: Step, w_att: Any, w_ranges: Any) -> None:
    """One step's attitude samples and valid range readings (with their true distances)."""
    for a in step.attitudes:
        w_att.writerow(
            [
                a.time_us,
                *(f"{v:.12f}" for v in a.quat_wxyz),
                *(f"{v:.9f}" for v in a.rates_rad_s),
            ]
        )
    for r in step.ranges:
        if r.sample is None:
            continue
        s = r.sample
        w_ranges.writerow(
            [
                s.time_us,
                s.sensor_id,
                f"{s.distance_m:.6f}",
                f"{s.min_m:.3f}",
                f"{s.max_m:.3f}",
                s.signal_quality,
                f"{r.true_distance_m:.6f}",
            ]
        )


def _write_calibration(cfg: Config, out_dir: Path) -> None:
    """calibration.toml: camera and rangefinders in our schema, and every mount as a matrix."""
    calib = {
        "camera": to_dict(cfg.camera),
        "rangefinders": to_dict(cfg.rangefinders),
        "matrices": {
            "T_body_cam": cfg.camera.T_body_cam().tolist(),
            **{
                f"T_body_rf{r.sensor_id}": r.mount.T_body_sensor().tolist()
                for r in cfg.rangefinders
            },
        },
    }
    (out_dir / "calibration.toml").write_text(
        "# Camera intrinsics/distortion and every sensor mount, in companion's config schema.\n"
        "# [matrices] repeats the mounts as 4x4 T_body_sensor (row-major) for other tools.\n"
        + tomli_w.dumps(calib)
    )


def _write_meta(cfg: Config, scenario: Scenario, out_dir: Path) -> None:
    """meta.toml: format and software versions, frames, path length and the SITL settings."""
    meta = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "software": __version__,
        "frames": scenario.n_frames,
        "path_length_m": scenario.trajectory.path_length_m(),
        "sitl": to_dict(cfg.sitl),
    }
    (out_dir / "meta.toml").write_text(tomli_w.dumps(meta))


def contact_sheet(
    dataset: Dataset, out: str | Path | None = None, n: int = 12, cols: int = 4
) -> Path:
    """Tile ``n`` evenly spaced frames (half size, time-stamped) into one PNG; returns its path."""
    if len(dataset) == 0:
        raise DatasetError(f"{dataset.path}: no frames")
    idx = np.unique(np.linspace(0, len(dataset) - 1, n).round().astype(int))
    tiles = []
    for i in idx:
        f = dataset.load_frame(int(i))
        tile = cv2.resize(f.image_bgr, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
        t_s = (f.time_us - dataset.frame_times_us[0]) * 1e-6
        cv2.putText(
            tile,
            f"#{i}  t={t_s:.1f}s",
            (6, 18),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )
        tiles.append(tile)
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[r : r + cols]) for r in range(0, len(tiles), cols)]
    sheet = np.vstack(rows)
    path = Path(out) if out is not None else dataset.path / "contact_sheet.png"
    if not cv2.imwrite(str(path), sheet):
        raise DatasetError(f"cannot write {path}")
    return path
