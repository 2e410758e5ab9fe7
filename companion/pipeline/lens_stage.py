"""The in-flight check of the camera's lens (companion/vo/focal_check.py): each VO keyframe's
tracked pixels with the autopilot's attitude at its time, the focal ratio f_true / f_file and
the k1 error k1_true - k1_file over a window of keyframe pairs, and one warning (with the
values that fit) once either is confidently off."""

from __future__ import annotations

import logging

from companion.geometry.camera import CameraModel
from companion.types import F64, VoOutput, VoState
from companion.vo.focal_check import FocalCheck, FocalRatio, KeyframeView, lens_findings

log = logging.getLogger("companion.pipeline")
MAX_WAITING = 8  # keyframes kept for the next work() before observe() pairs them itself


class LensStage:
    """Keyframes in (:meth:`observe`, in the frame's step: a copy of its pixels), the pairs'
    estimates when the keyframe work runs (:meth:`work`), the estimate and the warning out."""

    def __init__(self, camera: CameraModel, T_body_cam: F64) -> None:
        self.check = FocalCheck(camera)
        self.R_body_cam = T_body_cam[:3, :3].copy()
        self._waiting: list[KeyframeView] = []
        self.warning: str | None = None  # the warning, once given (it is given once)
        self.brief: str | None = None  # its short form ("k1 +0.021"), for the ground station

    def observe(self, out: VoOutput, R_world_body: F64 | None, segment: int) -> None:
        """Keep a tracked keyframe that has the autopilot's attitude at its time."""
        if out.state != VoState.TRACKING or not out.is_keyframe or R_world_body is None:
            return
        has = out.features.point_ids >= 0
        view = KeyframeView(
            out.time_us,
            segment,
            R_world_body @ self.R_body_cam,
            out.features.point_ids[has].copy(),
            out.features.pixels[has].copy(),
        )
        self._waiting.append(view)
        if len(self._waiting) >= MAX_WAITING:  # nobody runs the keyframe work (run_scale)
            self.work()

    def work(self) -> bool:
        """Pair the keyframes kept since the last call; whether there were any."""
        if not self._waiting:
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
        return True

    def estimate(self) -> FocalRatio | None:
        """The focal ratio so far (FocalCheck.estimate)."""
        return self.check.estimate()

    def result(self) -> FocalRatio | None:
        """The estimate once every kept keyframe is paired (the end of an offline run)."""
        self.work()
        return self.estimate()
