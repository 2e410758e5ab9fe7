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

Nothing is done when none of them is on (the default), so frames stay those of before.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.geometry import se3
from companion.types import F64

if TYPE_CHECKING:
    from companion.sitl.world.render import RenderedFrame, Renderer

SHADOW_DEPTH = 0.55  # the share of a sunlit level ground's light that is direct (1 - ambient)
SKY_BGR = np.array([200.0, 170.0, 150.0])  # the renderer's sky, in the water
_ON_GROUND_M = 0.03  # a point this close to the height field is ground, not a roof or wall
_WAVE_HZ, _WAVE_M, _FLUTTER_HZ = 4.0, 0.5, 6.8


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
    h, w = frame.depth_m.shape
    depth = frame.depth_m.ravel().astype(np.float64)
    ok = np.isfinite(depth)
    rays = renderer.rays_cam
    p_cam = rays * np.where(ok, depth / rays[:, 2], 0.0)[:, None]
    p_world = se3.transform(frame.T_world_cam, p_cam)
    ground_h = np.full(h * w, np.nan)
    ground_h[ok] = world.height(p_world[ok, 0], p_world[ok, 1])
    on_ground = ok & (np.abs(p_world[:, 2] + ground_h) < _ON_GROUND_M)
    image = frame.image_bgr.reshape(-1, 3)
    out = image.astype(np.float64)
    vehicle = T_world_body[:3, 3]
    if g.downwash_m > 0.0:
        _downwash(renderer, frame, p_world, on_ground, vehicle, time_s, out)
    if g.shadow:
        out[ok] *= shadow_factor(p_world[ok], vehicle, renderer.sun_ned, g.shadow_radius_m)[:, None]
    if world.specular is not None:
        wgt = np.zeros(h * w)
        wgt[on_ground] = world.specular.weight(p_world[on_ground, 0], p_world[on_ground, 1])
        lit = wgt > 0.0
        cam = frame.T_world_cam[:3, 3]
        glint = highlight(p_world[lit], cam, renderer.sun_ned, g.specular_exponent)
        water = 0.06 * SKY_BGR[None, :] + 255.0 * g.specular_strength * glint[:, None]
        wl = wgt[lit][:, None]
        out[lit] = out[lit] * (1.0 - 0.6 * wl) + wl * water
    image[:] = np.clip(np.floor(out + 0.5), 0, 255).astype(np.uint8)


def shadow_factor(points_world: F64, vehicle_world: F64, sun_ned: F64, radius_m: float) -> F64:
    """Light left (N,) in [1 - SHADOW_DEPTH, 1] at points (N, 3) NED [m] by the vehicle's soft
    shadow: the vehicle a disc of ``radius_m`` at ``vehicle_world`` (3,), the sun towards the
    unit vector ``sun_ned`` (3,)."""
    q = vehicle_world[None, :] - points_world
    along = q @ sun_ned
    d = np.linalg.norm(q - along[:, None] * sun_ned[None, :], axis=1)
    soft = 0.08 + 0.01 * np.maximum(along, 0.0)
    x = np.clip((radius_m + soft - d) / (2.0 * soft), 0.0, 1.0)
    cover = np.where(along > 0.0, x * x * (3.0 - 2.0 * x), 0.0)
    return np.asarray(1.0 - SHADOW_DEPTH * cover, dtype=np.float64)


def highlight(points_world: F64, camera_world: F64, sun_ned: F64, exponent: float) -> F64:
    """Phong lobe (N,) in [0, 1] of level water at points (N, 3) NED seen from camera_world (3,):
    max(0, r.v)^exponent, r the sun's mirror direction about the up normal, v towards the camera."""
    up = np.array([0.0, 0.0, -1.0])
    mirror = 2.0 * float(up @ sun_ned) * up - sun_ned
    v = camera_world[None, :] - points_world
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return np.asarray(np.maximum(v @ mirror, 0.0) ** exponent, dtype=np.float64)


def downwash_offset(
    points_world: F64, vehicle_world: F64, time_s: float, amp_m: float, radius_m: float
) -> F64:
    """Horizontal displacement (N, 3) [m] (z = 0) of the grass at points (N, 3) NED by the
    downwash of a vehicle at vehicle_world (3,) at ``time_s`` (module docstring)."""
    rel = points_world[:, :2] - vehicle_world[None, :2]
    r = np.linalg.norm(rel, axis=1)
    radial = rel / np.maximum(r, 1e-6)[:, None]
    tangent = np.stack([-radial[:, 1], radial[:, 0]], axis=1)
    envelope = amp_m * np.exp(-((r / radius_m) ** 2))
    push = 0.5 + 0.5 * np.sin(2 * math.pi * (_WAVE_HZ * time_s - r / _WAVE_M))
    flutter = 0.3 * np.sin(2 * math.pi * _FLUTTER_HZ * time_s + 9.0 * rel[:, 0] + 7.0 * rel[:, 1])
    out = np.zeros_like(points_world)
    out[:, :2] = envelope[:, None] * (push[:, None] * radial + flutter[:, None] * tangent)
    return out


def _downwash(
    renderer: Renderer,
    frame: RenderedFrame,
    p_world: F64,
    on_ground: NDArray[np.bool_],
    vehicle: F64,
    time_s: float,
    out: F64,
) -> None:
    """Resample the ground pixels near the vehicle's ground point at P - D(P, t)."""
    g = renderer.world.ground
    near = on_ground & (
        np.linalg.norm(p_world[:, :2] - vehicle[None, :2], axis=1) < 3.0 * g.downwash_radius_m
    )
    if not near.any():
        return
    src = p_world[near] - downwash_offset(
        p_world[near], vehicle, time_s, g.downwash_m, g.downwash_radius_m
    )
    uv, _ = renderer.model.project(se3.transform(se3.inverse(frame.T_world_cam), src))
    n = len(uv)
    maps = np.zeros((2, -(-n // 512) * 512), dtype=np.float32)  # remap takes <= 32767 columns
    maps[:, :n] = uv.T
    sampled = cv2.remap(
        frame.image_bgr,
        maps[0].reshape(-1, 512),
        maps[1].reshape(-1, 512),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    out[near] = sampled.reshape(-1, 3)[:n].astype(np.float64)
