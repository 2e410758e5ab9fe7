"""A dataset in memory (``Dataset``): the calibration, the time-stamped inputs in the order
the pipeline takes them, ground truth when known; its frames decoded lazily under the
folder's discipline. ``dataset_steps`` groups the inputs per frame for offline evaluation."""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import Config, SitlConfig
from companion.drivers.dataset.format import I64, Event, PublishedPose, RowCount
from companion.drivers.safe_files import (
    MAX_IMAGE_BYTES,
    SafeFolder,
    check_image_header,
)
from companion.errors import DatasetError
from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.geometry.lens_check import lens_problem
from companion.types import (
    F64,
    AttitudeSample,
    CameraFrame,
    ImuSample,
    RangeSample,
    RangeSensorSpec,
)


@dataclass
class Dataset:
    """A recording: calibration, time-stamped inputs and (when known) ground truth.

    frame_times_us: (F,) int64; frame_paths: F image files. gt_times_us: (G,) int64 and
    gt_T_world_body: (G, 4, 4) (world NED, body FRD). true_range_m: (len(ranges),) true
    distances when simulated (NaN otherwise). sitl: the simulator settings that rebuild the
    world for ground-truth ray casting (None unless the dataset declares a simulated world).
    rangefinders: the sensors the dataset declares (none: no ranges, none invented).
    frame_seqs (F,): the recorded sequence numbers (None: the index). fed_before: for a
    recording, the index of the frame each range (R,) and attitude (A,) sample was fed before
    (the exact ingest order of the run); None: merge by time. imus: the accelerometer samples
    (imu.csv, optional) and imu_fed (I,) their frame indices in a recording. frames_checked:
    the recorded frames passed the service's frame check (a replay must not check them again).
    published: the poses the service sent (a recording's published.csv). complete: False
    for a recording that did not close (a crash, SIGKILL, power loss): it was read up to its
    last complete frame. image_bytes: the encoded image (PNG, JPEG) of a frame by index, for
    a dataset whose frames are not files (an MCAP recording: frame_paths is then empty).
    """

    path: Path
    kind: str
    camera: CameraModel
    T_body_cam: F64
    rangefinders: list[RangeSensorSpec]
    frame_times_us: I64
    frame_paths: list[Path]
    ranges: list[RangeSample] = field(default_factory=list)
    true_range_m: F64 = field(default_factory=lambda: np.zeros(0))
    attitudes: list[AttitudeSample] = field(default_factory=list)
    gt_times_us: I64 = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    gt_T_world_body: F64 = field(default_factory=lambda: np.zeros((0, 4, 4)))
    sitl: SitlConfig | None = None
    config: Config | None = None
    frame_seqs: I64 | None = None
    fed_before: tuple[I64, I64] | None = None
    frames_checked: bool = False
    published: list[PublishedPose] = field(default_factory=list)
    complete: bool = True
    meta: dict[str, Any] = field(default_factory=dict)
    imus: list[ImuSample] = field(default_factory=list)
    imu_fed: I64 | None = None
    frame_held: NDArray[np.bool_] | None = None  # (F,) frames the service held from its VO
    folder: SafeFolder | None = None  # where the files are read from (drivers/safe_files.py)
    frame_names: list[str] = field(default_factory=list)  # (F,) as frames.csv names them
    skipped: dict[str, RowCount] = field(default_factory=dict)  # per file: rows left out
    image_bytes: Callable[[int], bytes] | None = None  # frame index -> its encoded image

    def __len__(self) -> int:
        return len(self.frame_times_us)

    @property
    def has_world(self) -> bool:
        """Whether the dataset declares a simulated world (ray casting gives true depths)."""
        return self.sitl is not None

    @property
    def has_ground_truth(self) -> bool:
        return len(self.gt_times_us) > 0

    def load_frame(self, index: int) -> CameraFrame:
        """Read frame ``index`` as BGR (grey images are expanded to three channels): a regular
        file inside the folder whose header has the calibration's size (checked before it is
        decoded); DatasetError naming the frame otherwise."""
        size = (self.camera.width, self.camera.height)
        if self.image_bytes is not None:
            img = decode_image(self.image_bytes(index), size, f"{self.path} frame {index}")
        elif self.folder is not None and index < len(self.frame_names):
            img = decode_frame(self.folder, self.frame_names[index], size, f"frame {index}")
        else:
            path = self.frame_paths[index]
            img = decode_frame(SafeFolder(path.parent), path.name, size, f"frame {index}")
        seq = index if self.frame_seqs is None else int(self.frame_seqs[index])
        return CameraFrame(int(self.frame_times_us[index]), seq, img)

    def skipped_text(self) -> list[str]:
        """One line per file with rows the reader left out: how many and the first reason."""
        return [
            f"{name}: {c.skipped} bad row{'s' if c.skipped > 1 else ''} left out (first: {c.first})"
            for name, c in self.skipped.items()
        ]

    def frames(self) -> Iterator[CameraFrame]:
        """Frames in time order, loaded lazily."""
        for i in range(len(self)):
            yield self.load_frame(i)

    def events(self) -> Iterator[Event]:
        """All inputs in the order the pipeline takes them: a recording's exact ingest order
        (per frame: its attitudes, its ranges, the frame), else merged in time order (at
        equal times attitude and ranges precede a frame)."""
        if self.fed_before is not None:
            yield from self._fed_events(*self.fed_before)
            return
        streams: list[Iterator[tuple[int, int, int, Any]]] = [
            ((a.time_us, 0, i, a) for i, a in enumerate(self.attitudes)),
            ((r.time_us, 1, i, r) for i, r in enumerate(self.ranges)),
            ((m.time_us, 1, i, m) for i, m in enumerate(self.imus)),
            ((int(t), 2, i, i) for i, t in enumerate(self.frame_times_us)),
        ]
        for _, kind, _, item in heapq.merge(*streams):
            yield self.load_frame(item) if kind == 2 else item

    def _fed_events(self, range_frame: I64, att_frame: I64) -> Iterator[Event]:
        ri = ai = mi = 0
        imu_frame = np.zeros(0, dtype=np.int64) if self.imu_fed is None else self.imu_fed
        for k in range(len(self)):
            while ai < len(self.attitudes) and att_frame[ai] == k:
                yield self.attitudes[ai]
                ai += 1
            while mi < len(imu_frame) and mi < len(self.imus) and imu_frame[mi] == k:
                yield self.imus[mi]
                mi += 1
            while ri < len(self.ranges) and range_frame[ri] == k:
                yield self.ranges[ri]
                ri += 1
            if self.frame_held is None or not self.frame_held[k]:
                yield self.load_frame(k)

    def gt_pose_at(self, time_us: int) -> F64:
        """Ground-truth T_world_body interpolated at ``time_us`` (clamped to the recording)."""
        if len(self.gt_times_us) == 0:
            raise DatasetError(f"{self.path}: no ground truth")
        t = self.gt_times_us
        i = int(np.searchsorted(t, time_us))
        if i <= 0 or i >= len(t):
            return np.array(self.gt_T_world_body[0 if i <= 0 else -1], dtype=np.float64)
        a = (time_us - t[i - 1]) / float(t[i] - t[i - 1])
        return se3.interpolate(self.gt_T_world_body[i - 1], self.gt_T_world_body[i], a)


@dataclass(frozen=True, slots=True)
class _Reading:
    """A recorded range reading in the shape of the simulator's TrueRange."""

    sample: RangeSample | None
    true_distance_m: float


@dataclass(frozen=True, slots=True)
class DatasetStep:
    """One frame of a dataset with the samples since the previous frame and its ground truth,
    in the shape of ``sitl.scenario.Step`` (so offline evaluation takes either)."""

    frame: CameraFrame
    T_world_body: F64
    ranges: list[_Reading]
    attitudes: list[AttitudeSample]
    imus: list[ImuSample] = field(default_factory=list)


def dataset_steps(ds: Dataset) -> Iterator[DatasetStep]:
    """Frames of a dataset with the samples fed before each (in the dataset's ingest order)
    and its true pose (all NaN without ground truth)."""
    ranges: list[_Reading] = []
    atts: list[AttitudeSample] = []
    imus: list[ImuSample] = []
    truth = ds.true_range_m if len(ds.true_range_m) == len(ds.ranges) else None
    index = {id(r): i for i, r in enumerate(ds.ranges)}
    no_truth = np.full((4, 4), np.nan)
    for ev in ds.events():
        if isinstance(ev, AttitudeSample):
            atts.append(ev)
        elif isinstance(ev, RangeSample):
            t = float(truth[index[id(ev)]]) if truth is not None else float("nan")
            ranges.append(_Reading(ev, t))
        elif isinstance(ev, ImuSample):
            imus.append(ev)
        else:
            T = ds.gt_pose_at(ev.time_us) if ds.has_ground_truth else no_truth
            yield DatasetStep(ev, T, ranges, atts, imus)
            ranges, atts, imus = [], [], []


def decode_frame(
    folder: SafeFolder, name: str, size: tuple[int, int], where: str
) -> NDArray[np.uint8]:
    """The BGR image of file ``name``: read under the folder's discipline, its header's size
    checked against ``size`` (the calibration's) before it is decoded."""
    data = folder.read_bytes(name, MAX_IMAGE_BYTES, f"{where} ({name})")
    return decode_image(data, size, f"{where} ({name})")


def decode_image(data: bytes, size: tuple[int, int], where: str) -> NDArray[np.uint8]:
    """The BGR image (grey ones expanded to three equal channels) of PNG or JPEG bytes,
    their header's size checked against ``size`` before they are decoded."""
    check_image_header(data, where, size)
    flags = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    if img is None or img.shape[:2] != (size[1], size[0]):
        raise DatasetError(f"{where}: the image does not decode")
    return np.asarray(img, dtype=np.uint8)


def check_lens(model: CameraModel, where: str, dist_key: str = "dist") -> None:
    """DatasetError naming ``where`` (the file and table) and ``dist_key`` unless the camera
    model can serve the pipeline over its whole image: finite, positive intrinsics, a radial
    distortion that increases up to the image's corners and an undistortion that converges
    on every border pixel and a grid inside (``companion.geometry.lens_check``; a hostile
    or broken calibration made the VO raise deep inside a run)."""
    problem = lens_problem(model)
    if problem is not None:
        raise DatasetError(f"{where} {dist_key}: the camera model cannot be used: {problem}")
