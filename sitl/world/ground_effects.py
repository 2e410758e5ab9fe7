"""What on the ground changes with the camera and the time: water-like specular patches, the
vehicle's own shadow and grass in the rotors' downwash ([sitl.ground], companion/sitl_options.py).

Applied to a finished frame (``apply``, one call at the end of ``Renderer.render_at``): every
pixel's world point comes from the frame's z-depth and the camera's pixel rays, P_world =
T_world_cam (ray * depth / ray_z); then, in this order,

- downwash: a ground point P shows the grass of P - D(P, t), D horizontal [m] with amplitude
  ``downwash_m`` * exp(-(r / R)^2) at distance r from the vehicle's ground point (R =
  ``downwash_radius_m``): a radial push pulsing at 4 Hz in waves that run outward at 2 m/s, and a
  tangential flutter at 6.8 Hz; the pixel is resampled (bilinear) at the projection of P - D;
- shadow: a point P is in the vehicle's shadow when the ray from P towards the sun passes within
  ``shadow_radius_m`` of the vehicle's centre V: its distance d from V's line, with a penumbra of
  8 cm + 1 cm per metre of P to V (the sun's disc and the rotors' blur); in full shadow the direct
  light is gone and the ambient part stays (the renderer's ambient 0.45 of a sunlit level ground);
- specular patches (surfaces.SpecularPatches, weight w): water keeps 40 % of the ground's diffuse
  light, reflects 6 % of the sky, and adds a Phong highlight ``strength`` * 255 * max(0, r.v)^p,
  r the sun's mirror direction about the level water's normal, v the direction to the camera:
  the highlight sits where the camera sees the sun's reflection, so it moves with the camera.

Nothing is done when none of them is on (the default), so frames stay those of before. The
per-pixel work is one compiled loop (_ground_kernel.py): ~20x fewer operations than array
passes over the whole frame.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.geometry import se3
from companion.sitl.world._ground_kernel import (
    SHADOW_DEPTH,
    SKY_BGR,
    apply_effects,
    downwash_sources,
)
from companion.types import F64, U8

if TYPE_CHECKING:
    from companion.sitl.world.render import RenderedFrame, Renderer

__all__ = ["SHADOW_DEPTH", "SKY_BGR", "any_on", "apply"]

_NO_WATER = np.zeros((0, 0), dtype=np.float32)
_NONE_MOVED = np.zeros(0, dtype=np.int64)
_NO_BGR = np.zeros((0, 3), dtype=np.uint8)


def any_on(renderer: Renderer) -> bool:
    """Whether the world's ground has an effect that changes with the camera or the time."""
    g = renderer.world.ground
    return renderer.world.specular is not None or g.shadow or g.downwash_m > 0.0


def apply(renderer: Renderer, frame: RenderedFrame, T_world_body: F64, time_s: float) -> None:
    """The ground's moving effects on ``frame.image_bgr`` (H, W, 3) uint8, in place, for the
    vehicle at T_world_body (4, 4) NED at ``time_s`` [s]."""
    if not any_on(renderer):
        return
    world, g = renderer.world, renderer.world.ground
    depth = np.ascontiguousarray(frame.depth_m.ravel(), dtype=np.float64)
    T_world_cam = np.ascontiguousarray(frame.T_world_cam, dtype=np.float64)
    vehicle = np.ascontiguousarray(T_world_body[:3, 3], dtype=np.float64)
    height_field = (world.heights, 1.0 / world.res_m, world.x0, world.y0)
    moved, moved_bgr = _NONE_MOVED, _NO_BGR
    if g.downwash_m > 0.0:
        moved, moved_bgr = _downwash(renderer, frame, depth, T_world_cam, vehicle, time_s)
    water = world.specular
    image = frame.image_bgr.reshape(-1, 3)
    out = np.empty_like(image)
    apply_effects(
        image,
        depth,
        renderer.rays_cam,
        T_world_cam,
        *height_field,
        moved,
        moved_bgr,
        vehicle,
        np.array([1.0 if g.shadow else 0.0, g.shadow_radius_m]),
        renderer.sun_ned,
        _NO_WATER if water is None else water.grid,
        np.array(
            [
                0.0 if water is None else water.x0,
                0.0 if water is None else water.inv_cell,
                g.specular_strength,
                g.specular_exponent,
            ]
        ),
        out,
    )
    image[:] = out


def _downwash(
    renderer: Renderer,
    frame: RenderedFrame,
    depth: F64,
    T_world_cam: F64,
    vehicle: F64,
    time_s: float,
) -> tuple[NDArray[np.int64], U8]:
    """The ground pixels near the vehicle's ground point (n,) and what they show now (n, 3):
    the frame resampled (bilinear, cv2.remap) at the projection of P - D(P, t)."""
    world, g, m = renderer.world, renderer.world.ground, renderer.model
    uv = np.empty((len(depth), 2))
    moved = downwash_sources(
        depth,
        renderer.rays_cam,
        T_world_cam,
        se3.inverse(T_world_cam),
        world.heights,
        1.0 / world.res_m,
        world.x0,
        world.y0,
        np.array([m.fx, m.fy, m.cx, m.cy, m.k1, m.k2, m.p1, m.p2, m.k3]),
        vehicle,
        float(time_s),
        np.array([g.downwash_m, g.downwash_radius_m]),
        uv,
    )
    n = len(moved)
    if n == 0:
        return _NONE_MOVED, _NO_BGR
    maps = np.zeros((2, -(-n // 512) * 512), dtype=np.float32)  # remap takes <= 32767 columns
    maps[:, :n] = uv[:n].T
    sampled = cv2.remap(
        frame.image_bgr,
        maps[0].reshape(-1, 512),
        maps[1].reshape(-1, 512),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return moved, np.ascontiguousarray(sampled.reshape(-1, 3)[:n])
