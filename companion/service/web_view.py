"""What the live page shows of one frame, handed from the pipeline's worker to the page, and
its drawing data made off the worker.

The worker's whole share (``LatestView.offer``) is one check of an int while nobody watches,
and with a viewer one small frozen ``WebView`` of references (the frame, the VO's output,
the scale's input, the status snapshot, the pose: none of them is changed after the frame,
the pipeline makes new ones each frame) put into a 1-slot holder. Everything else runs on
the page's own thread (``render``): the image downscaled and JPEG-encoded, the features and
laser dots turned into drawing coordinates, the laser dots' matched map points found again
as the scale found them (``companion.scale.msc.measure``, a pure function: the pipeline's
arithmetic is untouched).

Frames and units of the overlay: pixels of the image sent (the camera's scaled by
``scale = sent width / camera width``), depths [m] along the camera's z (the VO's depth times
the metric scale; None before a scale), ranges [m]. ``Track``: north/east [m] in the local
NED frame of the pose sent (ours) or of LOCAL_POSITION_NED (the autopilot's own).
"""

from __future__ import annotations

import json
from collections import deque
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.pipeline import PipelineStatus
from companion.scale import msc
from companion.scale.methods import ScaleInput
from companion.scale.options import ScaleOptions
from companion.types import CameraFrame, PoseEstimate, VoOutput

TRACK_POINTS = 4000  # points kept per track (at TRACK_STEP_M: 200 m of flight at least)
TRACK_STEP_M = 0.05  # a new track point once the vehicle moved this far [m]
TRACK_EVERY_S = 1.0  # ... or this long after the last one (a hover still shows as alive)


@dataclass(frozen=True, slots=True)
class WebView:
    """One frame as the worker left it: references only (nothing here is copied)."""

    frame: CameraFrame
    vo: VoOutput | None  # None: the frame was held or refused before the VO
    scale_input: ScaleInput | None  # None: not tracking (no lasers matched)
    status: PipelineStatus
    pose: PoseEstimate | None
    number: int  # the holder's count when offered (1, 2, ...)


class LatestView:
    """The 1-slot holder between the worker (``offer``) and the page (``take``).

    ``viewers`` is set by the page on the event loop and read by the worker thread (an int:
    atomic in CPython); while it is 0 ``offer`` does nothing and makes nothing. A new view
    replaces the one not yet taken: a slow page skips frames, it never queues them."""

    def __init__(self) -> None:
        self.viewers = 0
        self.offered = 0  # views handed over (the worker's only work for the page)
        self.latest: WebView | None = None

    def wanted(self) -> bool:
        return self.viewers > 0

    def offer(
        self,
        frame: CameraFrame,
        vo: VoOutput | None,
        scale_input: ScaleInput | None,
        status: PipelineStatus,
        pose: PoseEstimate | None,
    ) -> None:
        """Worker thread: the frame just processed, when somebody watches (else nothing)."""
        if self.viewers <= 0:
            return
        self.offered += 1
        self.latest = WebView(frame, vo, scale_input, status, pose, self.offered)

    def take(self, after: int) -> WebView | None:
        """The latest view if it is newer than number ``after`` (else None)."""
        view = self.latest
        return view if view is not None and view.number > after else None

    def clear(self) -> None:
        """Nobody watches any more: let the last frame go."""
        self.latest = None


class Track:
    """A top-down track: (north, east) [m] points, a new one every TRACK_STEP_M or
    TRACK_EVERY_S, at most TRACK_POINTS (the oldest dropped). ``total`` counts every point
    ever added, so that a viewer asks only for the ones it has not seen (``since``)."""

    def __init__(self, max_points: int = TRACK_POINTS) -> None:
        self.points: deque[tuple[float, float]] = deque(maxlen=max_points)
        self.total = 0
        self._last_s = -1e18

    def add(self, time_s: float, north_m: float, east_m: float) -> None:
        if not (np.isfinite(north_m) and np.isfinite(east_m)):
            return
        if self.points:
            n0, e0 = self.points[-1]
            moved = (north_m - n0) ** 2 + (east_m - e0) ** 2 >= TRACK_STEP_M**2
            if not moved and time_s - self._last_s < TRACK_EVERY_S:
                return
        self.points.append((round(north_m, 3), round(east_m, 3)))
        self.total += 1
        self._last_s = time_s

    def since(self, seen: int) -> tuple[int, list[tuple[float, float]]]:
        """(index of the first point returned, the points after the first ``seen`` ones);
        every point kept when some of those were dropped already."""
        new = self.total - max(seen, 0)
        if new <= 0:
            return self.total, []
        if new > len(self.points):
            return self.total - len(self.points), list(self.points)
        return self.total - new, list(self.points)[-new:]


@dataclass(frozen=True, slots=True)
class Rendered:
    """One view made ready to send: the JPEG and its overlay as JSON text."""

    number: int
    jpeg: bytes
    overlay_json: str


def render(
    view: WebView, camera: CameraModel, scale_opts: ScaleOptions, width: int, quality: int
) -> Rendered:
    """The page's thread: the image at most ``width`` px wide (0: as it is), JPEG at
    ``quality``, and the overlay (``overlay``) in that image's pixels."""
    img = view.frame.image_bgr
    h, w = img.shape[:2]
    scale = 1.0
    if 0 < width < w:
        scale = width / w
        img = cv2.resize(img, (width, max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
        raise ValueError("JPEG encoding failed")
    data = overlay(view, camera, scale_opts, scale, (img.shape[1], img.shape[0]))
    return Rendered(view.number, buf.tobytes(), json.dumps(data, allow_nan=False))


def overlay(
    view: WebView,
    camera: CameraModel,
    scale_opts: ScaleOptions,
    scale: float,
    size_px: tuple[int, int],
) -> dict[str, Any]:
    """The drawing data of one view (JSON-ready): ``features`` [[u, v, depth_m or None,
    has_point 0/1], ...], ``lasers`` [{id, u, v, range_m, match: [u, v] or None}], the
    frame's VO/scale/pose figures. Pixels are of the image sent (``scale`` times the
    camera's), rounded to 0.1 px."""
    st, pose = view.status, view.pose
    metric = st.scale if st.scale is not None and st.scale > 0 else None
    feats: list[list[Any]] = []
    out = view.vo
    if out is not None and len(out.features.pixels):
        f = out.features
        has = f.point_ids >= 0
        depth = np.full(len(has), np.nan)
        if metric is not None and has.any() and np.all(np.isfinite(out.T_vo_cam)):
            T_cam_vo = se3.inverse(out.T_vo_cam)
            depth[has] = se3.transform(T_cam_vo, f.points_vo[has])[:, 2] * metric
        uv = np.round(f.pixels * scale, 1)
        for (u, v), d, p in zip(uv.tolist(), depth.tolist(), has.tolist(), strict=True):
            feats.append([u, v, round(d, 2) if np.isfinite(d) else None, int(p)])
    return {
        "type": "frame",
        "number": view.number,
        "seq": view.frame.seq,
        "time_us": view.frame.time_us,
        "width": size_px[0],
        "height": size_px[1],
        "features": feats,
        "lasers": _lasers(view, camera, scale_opts, scale),
        "vo_state": st.vo_state,
        "keyframes": st.keyframes,
        "vo_resets": st.vo_resets,
        "scale": _num(st.scale),
        "scale_sigma": _num(st.scale_sigma),
        "scale_method": st.method,
        "sensors_used": st.sensors_used,
        "quality_pct": pose.quality_pct if pose is not None else None,
        "position_ned_m": _finite(pose.position_ned_m) if pose is not None else None,
        "roll_deg": _num(st.roll_deg),
        "pitch_deg": _num(st.pitch_deg),
    }


def _lasers(
    view: WebView, camera: CameraModel, opts: ScaleOptions, scale: float
) -> list[dict[str, Any]]:
    """Each distance sensor's dot at the frame (where its beam hits, projected) and the map
    point its MSC match takes (as ``companion.scale.msc.measure`` picks it), or None."""
    inp, out = view.scale_input, view.vo
    if inp is None or out is None:
        return []
    dots = []
    for sid, (range_m, p_cam, sigma_m) in inp.lasers.items():
        uv = msc.laser_pixel(camera, p_cam)
        if uv is None:
            continue
        m = msc.measure(
            sid,
            out.features,
            inp.T_cam_vo,
            camera,
            p_cam,
            sigma_m,
            opts.patch_half_px,
            opts.slope_factor,
            opts.edge_radius_px,
            opts.edge_depth_rel,
        )
        match = None
        if m is not None:
            i = np.flatnonzero(out.features.point_ids == m.point_id)
            if len(i):
                match = [round(float(c) * scale, 1) for c in out.features.pixels[i[0]]]
        dots.append(
            {
                "id": sid,
                "u": round(float(uv[0]) * scale, 1),
                "v": round(float(uv[1]) * scale, 1),
                "range_m": round(float(range_m), 3),
                "match": match,
            }
        )
    return dots


def _num(value: float | None) -> float | None:
    """A finite number as it is, anything else (None, NaN, inf) as None (JSON has no NaN)."""
    return float(value) if value is not None and np.isfinite(value) else None


def _finite(values: Any) -> list[float] | None:
    """A vector as a list of floats rounded to mm, or None when any is not finite."""
    arr = np.asarray(values, dtype=np.float64)
    return [round(float(x), 3) for x in arr] if np.all(np.isfinite(arr)) else None
