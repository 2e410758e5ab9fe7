"""How the SITL camera image is made (``[sitl.render]``): noise, motion blur, laser marks, and
the effects of a real camera, each off by default (issue "A simulator as hard as reality"):
a rolling shutter (``readout_ms``), the exposure as it changes (``[sitl.render.exposure]``) and
a lens that is not the configured one (``[sitl.render.lens_error]``).

Kept apart from ``companion/config.py`` (which holds them in ``SitlConfig.render``); the
renderer (``companion/sitl/world/render.py``) applies them, the VO never sees them: it keeps the
configured camera.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.geometry.lens_check import lens_problem
from companion.options import opt
from companion.types import F64

LaserMarkMode = Literal["off", "live", "painted"]


@dataclass(frozen=True, slots=True)
class ExposureOptions:
    """The brightness of each frame as a camera's auto-exposure makes it, and the lens's
    vignetting (``companion/sitl/world/exposure.py``: the model, deterministic in the seed and
    the frame's time). Every factor multiplies the linear image before noise and the 8-bit clip
    (so bright patches saturate at 255)."""

    steps_per_s: float = opt(
        0.0, "auto-exposure / gain steps per second, at random times (0 = none)", ge=0, le=30
    )
    step_max: float = opt(
        0.3, "largest brightness change of one step (fraction: 0.3 = +-30 %)", ge=0, le=0.5
    )
    drift: float = opt(0.0, "slow brightness drift, amplitude (fraction; 0 = none)", ge=0, le=0.5)
    drift_period_s: float = opt(30.0, "period of the slow drift [s]", gt=0, le=3600)
    clouds_per_min: float = opt(
        0.0, "the sun behind a cloud: dips per minute, at random times (0 = none)", ge=0, le=60
    )
    cloud_depth: float = opt(0.4, "light lost under a cloud (fraction)", ge=0, le=0.9)
    cloud_s: float = opt(4.0, "how long a cloud covers the sun [s]", gt=0, le=600)
    cloud_ramp_s: float = opt(1.0, "how long the light takes to fade in or out [s]", ge=0, le=60)
    vignetting: float = opt(
        0.0, "cos^4 falloff strength: 0 = none, 1 = the natural cos^4 of the ray angle", ge=0, le=1
    )

    @property
    def any(self) -> bool:
        """Whether any of these changes the image."""
        return self.frame_gain_varies or self.vignetting > 0

    @property
    def frame_gain_varies(self) -> bool:
        """Whether the brightness changes from frame to frame."""
        return (
            (self.steps_per_s > 0 and self.step_max > 0)
            or self.drift > 0
            or (self.clouds_per_min > 0 and self.cloud_depth > 0)
        )


@dataclass(frozen=True, slots=True)
class LensErrorOptions:
    """The lens the simulator renders with differs from the configured (calibrated) one by these
    errors; the VO, the scale and the evaluation keep the configured camera and mount."""

    focal: float = opt(
        0.0, "focal length error: rendered fx, fy = (1 + this) x the configured", ge=-0.2, le=0.2
    )
    principal_px: tuple[float, float] = opt(
        (0.0, 0.0),
        "principal point offset: rendered cx, cy = configured + this [px]",
        ge=-50,
        le=50,
    )
    k1: float = opt(
        0.0, "radial distortion error: rendered k1 = configured k1 + this", ge=-0.3, le=0.3
    )
    mount_deg: tuple[float, float, float] = opt(
        (0.0, 0.0, 0.0),
        "camera mount error: ZYX roll, pitch, yaw of the true camera in the configured one [deg]",
        ge=-10,
        le=10,
    )

    @property
    def any(self) -> bool:
        """Whether the rendered lens or mount differs from the configured one."""
        return (
            self.focal != 0.0
            or any(v != 0.0 for v in self.principal_px)
            or self.k1 != 0.0
            or any(v != 0.0 for v in self.mount_deg)
        )

    def rendered_model(self, configured: CameraModel) -> CameraModel:
        """The camera the renderer uses: fx, fy x (1 + focal), cx, cy + principal_px, k1 + k1."""
        if not self.any:
            return configured
        return replace(
            configured,
            fx=configured.fx * (1.0 + self.focal),
            fy=configured.fy * (1.0 + self.focal),
            cx=configured.cx + self.principal_px[0],
            cy=configured.cy + self.principal_px[1],
            k1=configured.k1 + self.k1,
        )

    def T_configured_rendered(self) -> F64:
        """(4, 4) the true camera frame in the configured camera frame: a rotation about the
        camera centre (ZYX ``mount_deg``), no translation."""
        return se3.from_xyz_rpy((0.0, 0.0, 0.0), np.radians(self.mount_deg))

    def problem(self, configured: CameraModel) -> str | None:
        """Why the rendered lens cannot be rendered (its distortion does not invert over the
        image), or None."""
        if not self.any:
            return None
        return lens_problem(self.rendered_model(configured))


@dataclass(frozen=True, slots=True)
class RenderConfig:
    """How the SITL camera image is made."""

    noise_sigma_dn: float = opt(2.0, "Gaussian pixel noise sigma [8-bit levels]", ge=0, le=50)
    motion_blur: bool = opt(False, "average sub-frames over the exposure time")
    exposure_s: float = opt(0.008, "exposure time for motion blur [s]", gt=0, le=0.1)
    blur_samples: int = opt(4, "sub-frames averaged for motion blur", ge=2, le=32)
    laser_marks: LaserMarkMode = opt("live", "laser dots: off, live (move) or painted (stay)")
    painted_time_s: float = opt(0.0, "time at which the painted marks are left [s]", ge=0)
    spot_diameter_m: float = opt(0.03, "laser spot diameter on the surface [m]", gt=0, le=1)
    sun_elevation_deg: float = opt(55.0, "sun elevation for shading [deg]", gt=0, le=90)
    sun_azimuth_deg: float = opt(140.0, "sun azimuth from north [deg]", ge=-360, le=360)
    readout_ms: float = opt(
        0.0,
        "rolling shutter: time to read the rows top to bottom [ms] (CSI/UVC: 10-30); "
        "0 = global shutter",
        ge=0,
        le=100,
    )
    exposure: ExposureOptions = opt(ExposureOptions(), "exposure changes and vignetting")
    lens_error: LensErrorOptions = opt(
        LensErrorOptions(), "the rendered lens against the configured one"
    )
