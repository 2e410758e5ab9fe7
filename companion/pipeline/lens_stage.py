"""The in-flight check of the camera's lens (companion/vo/focal_check.py): each VO keyframe's
tracked pixels with the autopilot's attitude at its time, the focal ratio f_true / f_file and
the k1 error k1_true - k1_file over a window of keyframe pairs, and one warning (with the
values that fit) once either is confidently off.

With ``[vo] learn_lens`` the lens that fits is also taken (once): the stage offers the
corrected camera model (:attr:`LensStage.learned`), and the pipeline gives it to every stage
that projects or undoes the lens and restarts the VO with it (a map's keyframes keep rays
of the old lens; the metric frame is carried across the restart)."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from companion.dpose.estimator import Dpose
from companion.geometry.camera import CameraModel
from companion.scale.methods import Method
from companion.types import F64, VoOutput, VoState
from companion.vo.focal_check import FocalCheck, FocalRatio, KeyframeView, lens_findings
from companion.vo.odometry import VisualOdometry

log = logging.getLogger("companion.pipeline")
MAX_WAITING = 8  # keyframes kept for the next work() before observe() pairs them itself


class LensStage:
    """Keyframes in (:meth:`observe`, in the frame's step: a copy of its pixels), the pairs'
    estimates when the keyframe work runs (:meth:`work`), the estimate and the warning out."""

    def __init__(self, camera: CameraModel, T_body_cam: F64, learn: bool = False) -> None:
        self.check = FocalCheck(camera)
        self.R_body_cam = T_body_cam[:3, :3].copy()
        self.learn = learn
        self._waiting: list[KeyframeView] = []
        self.warning: str | None = None  # the warning, once given (it is given once)
        self.brief: str | None = None  # its short form ("k1 +0.021"), for the ground station
        # with ``learn``: the lens that fits, once found, until the pipeline takes it (take())
        self.learned: CameraModel | None = None
        self.taken = 0  # lenses the pipeline took

    def observe(
        self,
        out: VoOutput,
        R_world_body: F64 | None,
        segment: int,
        pixels_at_stamp: Callable[[], F64] | None = None,
    ) -> bool:
        """Keep a tracked keyframe that has the autopilot's attitude at its time; whether a
        learned lens waits to be taken (:func:`take_lens`). ``pixels_at_stamp``: the
        features' pixels (N, 2) at the frame's stamp, in their order
        (VisualOdometry.pixels_at_stamp); None: as tracked. Under a rolling shutter each row
        is seen at its own time and the attitude is the stamp's: the simulated look-alike of
        rislab_downward (20 ms readout; the renderer's lens x1.01 and k1 +0.02 off the
        file's) read x1.124 and k1 -0.044, 133 of 200 pairs at an end of the search, from the
        rows as seen; x1.022 and +0.021 (76) from the features at the stamp (2026-12-01)."""
        if out.state != VoState.TRACKING or not out.is_keyframe or R_world_body is None:
            return self.learned is not None
        has = out.features.point_ids >= 0
        pixels = out.features.pixels if pixels_at_stamp is None else pixels_at_stamp()
        view = KeyframeView(
            out.time_us,
            segment,
            R_world_body @ self.R_body_cam,
            out.features.point_ids[has].copy(),
            pixels[has].copy(),
        )
        self._waiting.append(view)
        if len(self._waiting) >= MAX_WAITING:  # nobody runs the keyframe work (run_scale)
            self.work()
        return self.learned is not None

    def work(self, busy: bool = False) -> bool:
        """Pair the keyframes kept since the last call; whether there were any.

        ``busy``: the frame's work already built a keyframe or iterated the local BA; the
        pairing then waits for a frame without (at most ``MAX_WAITING`` keyframes: observe
        pairs them then), so that one frame does not carry both and the pose after it waits
        for less. The check reads its keyframes' own copies and finds the same, a frame or
        two later. Not with ``learn``: a lens found is taken the frame after the work that
        finds it, and the VO restarts with it as soon as it can."""
        if not self._waiting or (busy and not self.learn):
            return False
        for view in self._waiting:
            self.check.add(view)
        self._waiting.clear()
        est = self.check.estimate()
        if self.warning is None and est is not None:
            found = lens_findings(est, camera=self.check.camera)
            if found:
                self.warning = "; ".join(text for _, text in found)
                self.brief = ", ".join(brief for brief, _ in found)
                log.warning("%s", self.warning)
                if self.learn and self.taken == 0:
                    self.learned = fitted_lens(self.check.camera, est, [b for b, _ in found])
        return True

    def take(self) -> CameraModel | None:
        """The learned lens, once (None when there is none to take); the check goes on with
        it as the file's (a new window: what it finds next is relative to the new lens)."""
        camera, self.learned = self.learned, None
        if camera is not None:
            self.check = FocalCheck(camera)
            self._waiting.clear()
            self.taken += 1
            self.warning = (
                f"{self.warning}; learned in flight: fx {camera.fx:.1f}, fy {camera.fy:.1f}, "
                f"k1 {camera.k1:.4f} (the VO restarted with them; the check goes on from them)"
            )
            log.warning(
                "lens learned in flight: fx %.1f, fy %.1f, k1 %.4f; the VO restarts with it",
                camera.fx,
                camera.fy,
                camera.k1,
            )
        return camera

    def estimate(self) -> FocalRatio | None:
        """The focal ratio so far (FocalCheck.estimate)."""
        return self.check.estimate()

    def result(self) -> FocalRatio | None:
        """The estimate once every kept keyframe is paired (the end of an offline run)."""
        self.work()
        return self.estimate()


def fitted_lens(camera: CameraModel, est: FocalRatio, briefs: list[str]) -> CameraModel | None:
    """``camera`` with what the check found confidently wrong replaced by what fits: fx fy
    times the focal ratio ("focal" in ``briefs``), k1 plus its error ("k1"); None when the
    finding is that no lens in the search fits (nothing to take)."""
    if not any(b.startswith(("focal", "k1")) for b in briefs):
        return None
    q = est.ratio if any(b.startswith("focal") for b in briefs) else 1.0
    k1 = camera.k1 + (est.k1_delta if any(b.startswith("k1") for b in briefs) else 0.0)
    return dataclasses.replace(camera, fx=camera.fx * q, fy=camera.fy * q, k1=k1)


def give_lens(
    camera: CameraModel, vo: VisualOdometry, methods: Iterable[Method], dpose: Dpose | None
) -> None:
    """Every stage that projects or undoes the lens takes ``camera``: the VO (which drops its
    map: its keyframes' rays are of the old lens), the scale methods (the laser's pixel) and
    d-Pose (its marks' rays)."""
    vo.camera = camera
    vo.focal_px = 0.5 * (camera.fx + camera.fy)
    vo.lose()
    for method in methods:
        method.camera = camera
    if dpose is not None:
        dpose.camera = camera


def take_lens(
    stage: LensStage, vo: VisualOdometry, methods: Mapping[Any, Method], dpose: Dpose | None
) -> CameraModel:
    """The stage's learned lens given to the pipeline's stages (:func:`give_lens`; the scale
    methods by name); the camera model in use after it."""
    camera = stage.take()
    if camera is not None:
        give_lens(camera, vo, methods.values(), dpose)
    return vo.camera
