"""``companion dataset truth-check``: does a downward dataset's truth move like its images?

Tracks the floor between frames ``gap`` apart (every ``step``-th frame of the range asked),
then scores the truth's prediction of those tracks (companion/evaluation/truth_flow.py) at
a few time offsets of the truth against the frames' stamps, and optionally fits the lens.
A truth that explains most of the flow (a small error against the no-motion one) has its
mount, times and lens right; one that does not has a convention, a mount or a clock wrong,
whatever a VO run on it then says.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from companion.drivers.dataset.model import Dataset
from companion.errors import DatasetError
from companion.evaluation.truth_flow import (
    MIN_TRACKS,
    FloorPair,
    LensFit,
    fit_lens,
    no_motion_errors,
    pair_errors,
    track_floor,
    trimmed_mean,
)
from companion.types import F64


@dataclass(frozen=True, slots=True)
class Tracks:
    """Floor tracks of frame index a into frame index b: pixels (N, 2) each."""

    a: int
    b: int
    px_a: F64
    px_b: F64


@dataclass(frozen=True, slots=True)
class TruthCheck:
    """The check's figures: pairs and tracks used; the median over pairs of their median
    errors [px] of no motion, and of the truth at each offset tried (offset_s, median,
    trimmed mean); the offset of least median; the lens fitted at that offset (None unless
    asked)."""

    pairs: int
    tracks: int
    no_motion_px: float
    truth_px: tuple[tuple[float, float, float], ...]
    best_offset_s: float
    lens: LensFit | None


def floor_tracks(ds: Dataset, first: int, stop: int, gap: int, step: int) -> list[Tracks]:
    """Tracks between frame indices i and i + gap for i = first, first + step, ... < stop -
    gap (pairs with fewer than MIN_TRACKS tracks left out)."""
    out: list[Tracks] = []
    for i in range(first, min(stop, len(ds)) - gap, step):
        grey = [cv2.cvtColor(ds.load_frame(k).image_bgr, cv2.COLOR_BGR2GRAY) for k in (i, i + gap)]
        px_a, px_b = track_floor(grey[0], grey[1])
        if len(px_a) >= MIN_TRACKS:
            out.append(Tracks(i, i + gap, px_a, px_b))
    return out


def pairs_at(ds: Dataset, tracks: list[Tracks], offset_s: float) -> list[FloorPair]:
    """The tracks with the truth's camera poses at each frame's stamp + ``offset_s``."""
    shift_us = int(round(offset_s * 1e6))
    T_body_cam = ds.T_body_cam

    def pose(index: int) -> F64:
        T: F64 = ds.gt_pose_at(int(ds.frame_times_us[index]) + shift_us) @ T_body_cam
        return T

    return [FloorPair(t.px_a, t.px_b, pose(t.a), pose(t.b)) for t in tracks]


def check_truth(
    ds: Dataset,
    floor_z_m: float,
    frames: tuple[int, int] | None = None,
    gap: int = 3,
    step: int = 5,
    offsets_s: tuple[float, ...] = (0.0,),
    lens: bool = False,
) -> TruthCheck:
    """The floor's flow against the truth over frame indices ``frames`` (A, B) (default: all)
    of ``ds``, for each time offset; DatasetError when there is no truth or no usable pair."""
    if not ds.has_ground_truth:
        raise DatasetError(f"{ds.path}: no ground truth to check")
    first, stop = frames if frames is not None else (0, len(ds))
    tracks = floor_tracks(ds, first, stop, gap, step)
    if not tracks:
        raise DatasetError(
            f"{ds.path}: no pair of frames {gap} apart in {first}:{stop} with {MIN_TRACKS} "
            "floor tracks"
        )
    model = ds.camera
    pairs = {offset: pairs_at(ds, tracks, offset) for offset in offsets_s}
    scored = []
    for offset, at_offset in pairs.items():
        errors = pair_errors(model, at_offset, floor_z_m)
        scored.append((offset, float(np.median(errors)), trimmed_mean(errors)))
    best = min(scored, key=lambda s: s[1])[0]
    return TruthCheck(
        len(tracks),
        sum(len(t.px_a) for t in tracks),
        float(np.median(no_motion_errors(pairs[best]))),  # the tracks alone: any offset's
        tuple(scored),
        best,
        fit_lens(model, pairs[best], floor_z_m) if lens else None,
    )


def report_lines(check: TruthCheck) -> list[str]:
    """What ``companion dataset truth-check`` prints."""
    lines = [
        f"{check.pairs} pairs of frames, {check.tracks} floor tracks; no motion: "
        f"{check.no_motion_px:.2f} px (the median over pairs of their median flow)",
    ]
    for offset, median, trimmed in check.truth_px:
        share = 100.0 * (1.0 - median / check.no_motion_px) if check.no_motion_px > 0 else 0.0
        lines.append(
            f"truth at {1e3 * offset:+.0f} ms: {median:.2f} px ({share:.0f} % of the flow "
            f"explained; trimmed mean {trimmed:.2f} px)"
        )
    lines.append(f"best offset: {1e3 * check.best_offset_s:+.0f} ms")
    if check.lens is not None:
        f = check.lens
        lines.append(
            f"lens that explains it best: focal {f.focal_px:.1f} px, k1 {f.k1:+.4f}, "
            f"k2 {f.k2:+.4f} ({f.median_error_px:.2f} px; trimmed mean "
            f"{f.trimmed_error_px:.2f} px)"
        )
    return lines
