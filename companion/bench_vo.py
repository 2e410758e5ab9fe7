"""``companion bench vo``'s figures: the frame's cost as a ratio to its OpenCV floor.

Absolute times do not carry from one machine to another (the same code ran 3x slower on one
host than on another), so the frame is measured against a floor measured in the same run, on
the same frames: OpenCV's own pyramidal KLT (``cv2.calcOpticalFlowPyrLK``) of the features the
VO tracks from the frame before (its tracks once that frame's work is done), into this frame,
with the VO's window, levels and stop criteria and no initial flow: the one call no monocular
KLT VO can skip. The pose solve is not in that floor; a second one adds it: OpenCV's iterative
PnP (``cv2.solvePnP``, Levenberg-Marquardt from the pose of the frame before) on the frame's
own 2D-3D inliers, the least pose solve a map-based VO makes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.gc_pacing import GC_STAGE
from companion.pipeline import AFTER_POSE, Pipeline
from companion.types import CameraFrame, VoState

# The planning factors of a board's core against a laptop's for OpenCV work (a Raspberry
# Pi 4's Cortex-A72 about 5x slower, a Pi 5's Cortex-A76 about 2.5x): an estimate from
# published figures, not a measurement on the board
BOARD_FACTORS = {"pi4": 5.0, "pi5": 2.5}

# the VO's KLT stop criteria (companion/vo/frontend.py: track)
KLT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03)


@dataclass
class KltFloor:
    """The floor of every frame, measured beside the pipeline (``run_vo``'s ``observe``).

    ms: the KLT's wall time [ms] of each frame that had features in the frame before;
    features: how many it tracked; pnp_ms: the pose solve's wall time [ms] of each tracked
    frame whose tracks kept their normalised coordinates (not a keyframe's: its new corners
    have none yet)."""

    window_px: int
    levels: int
    ms: list[float] = field(default_factory=list)
    features: list[int] = field(default_factory=list)
    pnp_ms: list[float] = field(default_factory=list)
    _prev_gray: NDArray[np.uint8] | None = None
    _prev_px: NDArray[np.float32] | None = None

    def __call__(self, frame: CameraFrame, pipe: Pipeline) -> None:
        img = frame.image_bgr
        gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
        if self._prev_gray is not None and self._prev_px is not None and len(self._prev_px):
            w = self.window_px
            t0 = cv2.getTickCount()
            cv2.calcOpticalFlowPyrLK(
                self._prev_gray,
                gray,
                self._prev_px,
                None,
                winSize=(w, w),
                maxLevel=self.levels,
                criteria=KLT_CRITERIA,
            )
            self.ms.append((cv2.getTickCount() - t0) * 1e3 / cv2.getTickFrequency())
            self.features.append(len(self._prev_px))
        self._time_pnp(pipe)
        # what the VO's KLT tracks into the next frame: its tracks after this frame's work
        # (the candidates' check and a keyframe's new corners run after the pose)
        self._prev_gray = gray
        px = pipe.vo.tracks.px
        self._prev_px = np.ascontiguousarray(px, dtype=np.float32).reshape(-1, 1, 2)

    def _time_pnp(self, pipe: Pipeline) -> None:
        """OpenCV's iterative PnP of this frame's map points and their normalised
        coordinates (its inliers), from the pose of the frame before."""
        vo = pipe.vo
        out = pipe.vo_output
        tr = vo.tracks
        if out is None or out.state != VoState.TRACKING or tr.xy is None or len(tr.xy) != len(tr):
            return
        has = tr.pid >= 0
        if has.sum() < 6:
            return
        X = np.ascontiguousarray(vo.map.points_of(tr.pid[has]), dtype=np.float64)
        xy = np.ascontiguousarray(tr.xy[has], dtype=np.float64)
        rvec, _ = cv2.Rodrigues(vo.T_prev[:3, :3])
        tvec = vo.T_prev[:3, 3].reshape(3, 1).copy()
        t0 = cv2.getTickCount()
        cv2.solvePnP(X, xy, np.eye(3), None, rvec, tvec, True, cv2.SOLVEPNP_ITERATIVE)
        self.pnp_ms.append((cv2.getTickCount() - t0) * 1e3 / cv2.getTickFrequency())


@dataclass(frozen=True)
class FloorRatios:
    """The frame against its floor: floor_ms (median KLT), frame_ms (median time to the
    pose), p99_ms, keyframe_ms (median keyframe work) and their ratios to floor_ms."""

    floor_ms: float
    frame_ms: float
    p99_ms: float
    keyframe_ms: float

    @property
    def frame_ratio(self) -> float:
        return self.frame_ms / self.floor_ms

    @property
    def p99_ratio(self) -> float:
        return self.p99_ms / self.floor_ms

    @property
    def keyframe_ratio(self) -> float:
        return self.keyframe_ms / self.floor_ms

    def line(self) -> str:
        """The one line a script reads (``floor: KLT <ms> ms; frame median <ms> ms = <ratio>x
        floor; p99 <ratio>x; keyframe <ratio>x``)."""
        return (
            f"floor: KLT {self.floor_ms:.2f} ms; frame median {self.frame_ms:.2f} ms = "
            f"{self.frame_ratio:.2f}x floor; p99 {self.p99_ratio:.2f}x; "
            f"keyframe {self.keyframe_ratio:.2f}x"
        )


def floor_ratios(floor_ms: ArrayLike, frame_ms: ArrayLike, keyframe_ms: ArrayLike) -> FloorRatios:
    """The medians (and the frame's p99) of a run; keyframe_ms: the work after the pose of
    the frames that built a keyframe (NaN without any)."""
    floor, frame, kf = (np.asarray(a, dtype=np.float64) for a in (floor_ms, frame_ms, keyframe_ms))
    if not len(floor) or not len(frame):
        raise ValueError("no frame was tracked: no floor to compare with")
    return FloorRatios(
        float(np.median(floor)),
        float(np.median(frame)),
        float(np.percentile(frame, 99)),
        float(np.median(kf)) if len(kf) else float("nan"),
    )


def stage_table(stage_ms: Sequence[dict[str, float]], frame_ms: Sequence[float]) -> list[str]:
    """Markdown rows: each stage's frames, median and p99 [ms] where it ran, and its share of
    the run's time to the pose (stages after the pose: of the time after it). The VO's own
    stages are nested as ``vo: ...``."""
    names: list[str] = []
    for stages in stage_ms:
        names += [n for n in stages if n not in names]
    after = {*AFTER_POSE, GC_STAGE}
    total_to_pose = float(np.sum(frame_ms)) or 1.0
    total_after = sum(s.get(n, 0.0) for s in stage_ms for n in after) or 1.0
    rows = [
        "| stage | frames | median ms | p99 ms | share |",
        "|---|---:|---:|---:|---:|",
    ]
    for name in sorted(names, key=lambda n: (n in after, _stage_order(n, names))):
        ms = np.array([s[name] for s in stage_ms if name in s])
        if name in after:
            ms = ms[ms > 0.05]  # the frames that had work there
        if not len(ms):
            continue
        share = float(ms.sum()) / (total_after if name in after else total_to_pose)
        where = " (after the pose)" if name in after else ""
        rows.append(
            f"| {name}{where} | {len(ms)} | {np.median(ms):.3f} | "
            f"{np.percentile(ms, 99):.3f} | {100 * share:.1f} % |"
        )
    return rows


def _stage_order(name: str, names: list[str]) -> int:
    """The VO's own stages right below the VO's line."""
    if name.startswith("vo: "):
        return names.index("vo") if "vo" in names else 0
    return names.index(name)


@dataclass(frozen=True)
class WorkerDelays:
    """The service's worker replayed at the camera's stamps on the measured times.

    delay_ms (F,): how long each frame waited for the work of the frames before it (their
    keyframe work included); dropped: frames the worker skipped because a newer one had come
    (the service takes the newest frame)."""

    delay_ms: NDArray[np.float64]
    dropped: int


def worker_delays(time_us: Sequence[int], total_ms: Sequence[float]) -> WorkerDelays:
    """A model of companion/service's worker fed at the frames' capture times: it starts a
    frame when it arrives or when the work before it ends (the pose, then the keyframe work
    after it: ``total_ms``); of frames that arrived meanwhile, only the newest is worked on.
    The times are those measured one frame after another, so the model shows what the
    keyframe work does to the next pose."""
    t_ms = (np.asarray(time_us, dtype=np.float64) - float(time_us[0])) * 1e-3
    free_ms = 0.0
    delays: list[float] = []
    dropped = 0
    for i, arrival in enumerate(t_ms):
        if i + 1 < len(t_ms) and t_ms[i + 1] <= free_ms:
            dropped += 1  # a newer frame is waiting when the worker gets free
            continue
        start = max(float(arrival), free_ms)
        delays.append(start - float(arrival))
        free_ms = start + float(total_ms[i])
    return WorkerDelays(np.array(delays), dropped)
