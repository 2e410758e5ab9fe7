"""Check the distance sensors' extrinsics against images with the laser dots visible (pure).

For each image and each sensor with a reading ``range_m`` at that time, the model puts the
laser's hit point at (the range model of the scale estimators, companion/scale)

    p_body = T_body_rf @ (0, 0, range_m)          (the beam is +z of the sensor frame)
    uv_pred = project(T_cam_body @ p_body)          (full camera model, distortion included)

and the red dot the laser leaves should be found there. Dots are found with the d-Pose red-dot
detector (:func:`companion.dpose.detect.detect_marks`); in each image the predictions are
paired with the detected dots by a minimum-total-distance assignment (Hungarian), each pair
within ``search_radius_px``. Per sensor the report gives:

- ``offset_px`` = median over images of (detected - predicted), (du, dv) [px]: the systematic
  part; ``spread_px`` the RMS of the per-image offsets about it (detection and range noise);
- the **implied beam error**: the detected pixel's camera ray meets the sphere of radius
  ``range_m`` around the sensor origin at the point the beam really hit (the range is
  measured along the true beam), so ``u_obs = (p_hit - o_rf) / range_m`` is the observed beam
  direction in the body frame; ``beam_error_deg`` is the angle between the configured beam
  ``T_body_rf[:3, 2]`` and the mean observed beam;
- ``suggested_rpy_deg``: the mount angles that point the configured beam along the observed
  one, keeping the configured yaw (a beam fixes roll and pitch only): with
  ``v = Rz(yaw)^T u_obs`` and the ZYX convention of the config, ``roll = -asin(v_y)``,
  ``pitch = atan2(v_x, v_z)``;
- a verdict: OK, CHECK MOUNT (offset above ``max_offset_px`` or beam error above
  ``max_angle_deg``), NOT FOUND (the dot was missing near the prediction in too many images:
  a mount far off, or a dot the camera cannot see) or NO DATA (too few images where the model
  puts the dot inside the image with a valid range).

When every sensor is off by about the same pixel offset, the camera (its mount or intrinsics)
is the likelier culprit than every laser at once: the report says so.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from companion.dpose.detect import DetectOptions, detect_marks
from companion.errors import CalibrationError, GeometryError
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.options import opt
from companion.types import F64, RangeSensorSpec

U8 = NDArray[np.uint8]


@dataclass(frozen=True, slots=True)
class LaserCheckOptions:
    """Thresholds of ``companion calibrate lasers``."""

    max_offset_px: float = opt(3.0, "flag a sensor whose dot is farther from the model [px]", gt=0)
    max_angle_deg: float = opt(0.5, "flag a sensor whose implied beam error exceeds [deg]", gt=0)
    search_radius_px: float = opt(
        40.0, "a dot farther than this from the prediction is not the sensor's [px]", gt=0
    )
    min_images: int = opt(3, "images with the sensor's dot found needed for a verdict", ge=1)
    red_threshold: int = opt(
        90, "redness R - max(G, B) of a dot's pixels [8-bit levels]", ge=1, le=254
    )
    min_peak: int = opt(120, "a dot's brightest redness [8-bit levels]", ge=1, le=255)
    max_area_px: int = opt(400, "largest dot area [px] (larger red blobs are not dots)", ge=1)

    def detect_options(self) -> DetectOptions:
        """The red-dot detector's options."""
        return DetectOptions(
            threshold=self.red_threshold, min_peak=self.min_peak, max_area_px=self.max_area_px
        )


class Verdict(enum.StrEnum):
    """Per-sensor outcome."""

    OK = "OK"
    CHECK_MOUNT = "CHECK MOUNT"
    NOT_FOUND = "NOT FOUND"
    NO_DATA = "NO DATA"


@dataclass(frozen=True, slots=True)
class LaserFrame:
    """One image with the lasers on: ``image_bgr`` (H, W, 3) uint8 and the readings
    ``ranges_m`` {sensor_id: range along the beam [m]} taken at the same time."""

    name: str
    image_bgr: U8
    ranges_m: Mapping[int, float]


@dataclass(frozen=True, slots=True)
class DotObservation:
    """One sensor in one image: the model's ``predicted_px`` (2,) and the matched
    ``detected_px`` (2,) (NaN when no dot was within the search radius); ``u_obs_body`` (3,)
    the observed beam direction (NaN when not found), ``beam_error_deg`` its angle to the
    configured beam."""

    image: str
    range_m: float
    predicted_px: F64
    detected_px: F64
    u_obs_body: F64
    beam_error_deg: float

    @property
    def found(self) -> bool:
        """True when a dot was matched."""
        return bool(np.all(np.isfinite(self.detected_px)))


@dataclass(frozen=True, slots=True)
class SensorCheck:
    """The verdict on one sensor and the figures behind it (module docstring).

    ``offset_px`` (2,) median (du, dv) detected - predicted [px] and ``spread_px`` [px] are NaN
    without matches; ``suggested_rpy_deg`` is None then.
    """

    sensor_id: int
    verdict: Verdict
    n_predicted: int  # images with a valid range where the model puts the dot in the image
    n_found: int  # ... of which the dot was found near the prediction
    offset_px: F64
    spread_px: float
    beam_error_deg: float
    configured_rpy_deg: tuple[float, float, float]
    suggested_rpy_deg: tuple[float, float, float] | None
    observations: tuple[DotObservation, ...]

    @property
    def offset_norm_px(self) -> float:
        """|offset_px| [px]."""
        return float(np.hypot(*self.offset_px))


@dataclass(frozen=True, slots=True)
class LaserCheckReport:
    """All sensors' checks; ``common_offset_px`` (2,) the mean of their offsets; ``notes``
    for the user; ``stray_dots`` red dots matched to no sensor, over all images."""

    sensors: tuple[SensorCheck, ...]
    n_images: int
    common_offset_px: F64
    stray_dots: int
    notes: tuple[str, ...]
    opts: LaserCheckOptions

    @property
    def all_ok(self) -> bool:
        """True when every sensor's verdict is OK."""
        return all(s.verdict is Verdict.OK for s in self.sensors)

    def table(self) -> str:
        """A readable summary, one line per sensor."""
        head = (
            f"{'sensor':>6}  {'verdict':<11}  {'found':>7}  {'offset du,dv [px]':>18}  "
            f"{'|offset|':>8}  {'spread':>6}  {'beam err':>8}  suggested rpy_deg"
        )
        lines = [head]
        for s in self.sensors:
            du, dv = s.offset_px
            sugg = (
                "-"
                if s.suggested_rpy_deg is None or s.verdict is Verdict.OK
                else "[" + ", ".join(f"{a:.2f}" for a in s.suggested_rpy_deg) + "]"
            )
            lines.append(
                f"{s.sensor_id:>6}  {s.verdict.value:<11}  {s.n_found:>3}/{s.n_predicted:<3}  "
                f"{du:>+8.2f},{dv:>+8.2f}  {s.offset_norm_px:>8.2f}  {s.spread_px:>6.2f}  "
                f"{s.beam_error_deg:>7.2f}°  {sugg}"
            )
        lines.append(
            f"thresholds: |offset| <= {self.opts.max_offset_px:g} px and beam error <= "
            f"{self.opts.max_angle_deg:g}°; {self.n_images} images, {self.stray_dots} red dot(s) "
            "matched to no sensor"
        )
        lines.extend(f"note: {n}" for n in self.notes)
        return "\n".join(lines)

    def report(self) -> dict[str, object]:
        """Everything as plain JSON-able values."""

        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        def pair(a: F64) -> list[float | None]:
            return [num(float(v)) for v in a]

        return {
            "all_ok": self.all_ok,
            "images": self.n_images,
            "thresholds": {
                "max_offset_px": self.opts.max_offset_px,
                "max_angle_deg": self.opts.max_angle_deg,
                "search_radius_px": self.opts.search_radius_px,
            },
            "common_offset_px": pair(self.common_offset_px),
            "stray_dots": self.stray_dots,
            "notes": list(self.notes),
            "sensors": [
                {
                    "sensor_id": s.sensor_id,
                    "verdict": s.verdict.value,
                    "images_predicted": s.n_predicted,
                    "images_found": s.n_found,
                    "offset_px": pair(s.offset_px),
                    "offset_norm_px": num(s.offset_norm_px),
                    "spread_px": num(s.spread_px),
                    "beam_error_deg": num(s.beam_error_deg),
                    "configured_rpy_deg": list(s.configured_rpy_deg),
                    "suggested_rpy_deg": (
                        None if s.suggested_rpy_deg is None else list(s.suggested_rpy_deg)
                    ),
                    "observations": [
                        {
                            "image": o.image,
                            "range_m": o.range_m,
                            "predicted_px": pair(o.predicted_px),
                            "detected_px": pair(o.detected_px),
                            "beam_error_deg": num(o.beam_error_deg),
                        }
                        for o in s.observations
                    ],
                }
                for s in self.sensors
            ],
        }


def predict_dot_px(camera: CameraModel, T_cam_body: F64, T_body_rf: F64, range_m: float) -> F64:
    """Pixel (2,) [distorted] of the hit point ``range_m`` along the beam (+z of the sensor);
    NaN when it is behind the camera."""
    p_body = se3.transform(T_body_rf, np.array([0.0, 0.0, range_m]))
    uv, _ = camera.project(se3.transform(T_cam_body, p_body))
    return np.asarray(uv[0], dtype=np.float64)


def observed_beam_body(
    camera: CameraModel, T_body_cam: F64, origin_rf_body: F64, dot_px: F64, range_m: float
) -> F64 | None:
    """Unit beam direction (3,) in the body frame implied by a dot seen at ``dot_px`` (2,) and
    the reading ``range_m``: the camera ray through the dot meets the sphere of that radius
    around the sensor origin ``origin_rf_body`` (3,) [m] once in front of the camera (the
    camera is inside the sphere). None when the camera is not inside the sphere (a range
    shorter than the camera-sensor distance) or the pixel is outside the lens model."""
    try:
        ray_cam = camera.pixels_to_rays(dot_px)[0]
    except GeometryError:
        return None
    r = T_body_cam[:3, :3] @ ray_cam
    w = T_body_cam[:3, 3] - origin_rf_body
    b = float(r @ w)
    c = float(w @ w) - range_m**2
    if c >= 0.0:
        return None
    s = -b + math.sqrt(b * b - c)  # the positive root (the product of the roots is c < 0)
    u = (T_body_cam[:3, 3] + s * r - origin_rf_body) / range_m
    return np.asarray(u / np.linalg.norm(u), dtype=np.float64)


def rpy_for_beam_deg(u_body: F64, yaw_deg: float) -> tuple[float, float, float]:
    """ZYX (roll, pitch, yaw) [deg] whose sensor +z is ``u_body`` (3,), the yaw kept (see the
    module docstring)."""
    v = so3.rot_z(math.radians(yaw_deg)).T @ (u_body / np.linalg.norm(u_body))
    roll = -math.asin(float(np.clip(v[1], -1.0, 1.0)))
    pitch = math.atan2(float(v[0]), float(v[2]))
    return (math.degrees(roll), math.degrees(pitch), yaw_deg)


def _angle_deg(a: F64, b: F64) -> float:
    """Angle between two unit vectors [deg] (atan2 form: accurate for small angles)."""
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(a, b))), float(a @ b)))


def check_lasers(
    camera: CameraModel,
    T_body_cam: F64,
    sensors: Sequence[RangeSensorSpec],
    frames: Sequence[LaserFrame],
    opts: LaserCheckOptions | None = None,
) -> LaserCheckReport:
    """Check every sensor of ``sensors`` on ``frames`` (module docstring).

    ``T_body_cam`` (4, 4) camera -> body; each sensor's ``T_body_rf`` (4, 4) sensor -> body.
    Readings of sensors not in ``sensors`` raise CalibrationError; readings outside a sensor's
    [min_m, max_m] are skipped. Raises CalibrationError when no frame has a valid reading.
    """
    o = opts or LaserCheckOptions()
    if not sensors:
        raise CalibrationError("lasers: the config has no [[rangefinders]] to check")
    by_id = {s.sensor_id: s for s in sensors}
    T_cam_body = se3.inverse(T_body_cam)
    det_opts = o.detect_options()
    obs: dict[int, list[DotObservation]] = {s.sensor_id: [] for s in sensors}
    stray = 0
    stray_images: list[str] = []
    usable = 0
    for frame in frames:
        unknown = sorted(set(frame.ranges_m) - set(by_id))
        if unknown:
            raise CalibrationError(
                f"lasers: {frame.name}: sensor_id {unknown} not in the config (ids {sorted(by_id)})"
            )
        ids: list[int] = []
        pred: list[F64] = []
        for sid, d in sorted(frame.ranges_m.items()):
            spec = by_id[sid]
            if not (math.isfinite(d) and spec.min_m <= d <= spec.max_m):
                continue
            uv = predict_dot_px(camera, T_cam_body, spec.T_body_rf, d)
            if np.all(np.isfinite(uv)) and bool(camera.in_image(uv)[0]):
                ids.append(sid)
                pred.append(uv)
        if not ids:
            continue
        usable += 1
        dots = detect_marks(frame.image_bgr, det_opts)
        P = np.array(pred)
        match: dict[int, F64] = {}
        if len(dots):
            dist = np.linalg.norm(P[:, None, :] - dots[None, :, :], axis=2)
            rows, cols = linear_sum_assignment(np.where(dist <= o.search_radius_px, dist, 1e9))
            for i, j in zip(rows, cols, strict=True):
                if dist[i, j] <= o.search_radius_px:
                    match[i] = dots[j]
        n_stray = len(dots) - len(match)
        if n_stray:
            stray += n_stray
            stray_images.append(frame.name)
        for i, sid in enumerate(ids):
            spec = by_id[sid]
            d = float(frame.ranges_m[sid])
            u_cfg = spec.T_body_rf[:3, 2]
            det = match.get(i, np.full(2, np.nan))
            u_obs = None
            if i in match:
                u_obs = observed_beam_body(camera, T_body_cam, spec.T_body_rf[:3, 3], det, d)
            obs[sid].append(
                DotObservation(
                    frame.name,
                    d,
                    P[i],
                    det,
                    np.full(3, np.nan) if u_obs is None else u_obs,
                    math.nan if u_obs is None else _angle_deg(u_cfg, u_obs),
                )
            )
    if usable == 0:
        raise CalibrationError(
            f"lasers: none of the {len(frames)} image(s) has a valid range reading whose "
            "predicted dot falls inside the image"
        )
    checks = tuple(_sensor_check(by_id[sid], obs[sid], o) for sid in sorted(by_id))
    return _report(checks, len(frames), stray, stray_images, o)


def _sensor_check(
    spec: RangeSensorSpec, obs: list[DotObservation], o: LaserCheckOptions
) -> SensorCheck:
    rpy_cfg = tuple(float(math.degrees(a)) for a in so3.matrix_to_rpy(spec.T_body_rf[:3, :3]))
    rpy = (rpy_cfg[0], rpy_cfg[1], rpy_cfg[2])
    found = [x for x in obs if x.found]
    nan2 = np.full(2, np.nan)
    if len(found) < o.min_images:
        verdict = Verdict.NOT_FOUND if len(obs) >= o.min_images else Verdict.NO_DATA
        return SensorCheck(
            spec.sensor_id, verdict, len(obs), len(found), nan2, math.nan, math.nan, rpy, None,
            tuple(obs),
        )  # fmt: skip
    off = np.array([x.detected_px - x.predicted_px for x in found])
    median = np.median(off, axis=0)
    spread = float(np.sqrt(np.mean(np.sum((off - median) ** 2, axis=1))))
    u = np.array([x.u_obs_body for x in found if np.all(np.isfinite(x.u_obs_body))])
    beam_err, suggested = math.nan, None
    if len(u):
        u_mean = u.mean(axis=0)
        u_mean /= np.linalg.norm(u_mean)
        beam_err = _angle_deg(spec.T_body_rf[:3, 2], u_mean)
        suggested = rpy_for_beam_deg(u_mean, rpy[2])
    bad = float(np.hypot(*median)) > o.max_offset_px or beam_err > o.max_angle_deg
    verdict = Verdict.CHECK_MOUNT if bad else Verdict.OK
    return SensorCheck(
        spec.sensor_id, verdict, len(obs), len(found), median, spread, beam_err, rpy, suggested,
        tuple(obs),
    )  # fmt: skip


def _report(
    checks: tuple[SensorCheck, ...],
    n_images: int,
    stray: int,
    stray_images: list[str],
    o: LaserCheckOptions,
) -> LaserCheckReport:
    notes: list[str] = []
    for s in checks:
        if s.n_predicted and s.n_found < 0.5 * s.n_predicted:
            notes.append(
                f"sensor {s.sensor_id}: dot found in only {s.n_found} of {s.n_predicted} images "
                f"within {o.search_radius_px:g} px of the model (mount far off, dot too faint "
                "or outside the image?)"
            )
    measured = [s for s in checks if s.n_found >= o.min_images]
    common = np.mean([s.offset_px for s in measured], axis=0) if measured else np.full(2, np.nan)
    if len(measured) >= 3 and all(s.verdict is Verdict.CHECK_MOUNT for s in measured):
        resid = np.array([s.offset_px - common for s in measured])
        if float(np.max(np.linalg.norm(resid, axis=1))) < 0.5 * float(np.hypot(*common)):
            notes.append(
                f"every dot is shifted alike, by ({common[0]:+.1f}, {common[1]:+.1f}) px: "
                "check the camera ([camera.mount], intrinsics) before the sensors"
            )
    if stray:
        shown = ", ".join(stray_images[:3]) + (" ..." if len(stray_images) > 3 else "")
        notes.append(
            f"{stray} red dot(s) matched no sensor ({shown}): red objects or reflections, or a "
            f"dot more than {o.search_radius_px:g} px from the model"
        )
    return LaserCheckReport(checks, n_images, common, stray, tuple(notes), o)
