"""Compiled (numba) per-pixel pass of the ground's moving effects (ground_effects.py has the
model and its equations): downwash resampling, the vehicle's soft shadow, specular water.

One loop over the frame's pixels replaces a dozen full-frame array passes; each pixel reads the
untouched frame (the downwash samples it) and writes its own output, so the loop needs no
temporary larger than the image. World frame local NED; terrain height positive up (the ground
is z = -h(x, y), _kernels.py).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from companion.sitl.world._kernels import _height

# exact IEEE arithmetic: exp, sin and pow from libm, no reassociation (the effects are small
# and sit on rounding boundaries of the 8-bit image)
_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}

_WAVE_HZ, _WAVE_M, _FLUTTER_HZ = 4.0, 0.5, 6.8
_ON_GROUND_M = 0.03  # a point this close to the height field is ground, not a roof or wall
SHADOW_DEPTH = 0.55  # the share of a sunlit level ground's light that is direct (1 - ambient)
SKY_BGR = np.array([200.0, 170.0, 150.0])  # the renderer's sky, in the water


@nb.njit(inline="always", **_JIT)
def downwash_xy(rx, ry, time_s, amp_m, radius_m):
    """Horizontal displacement (dx, dy) [m] of the grass at (rx, ry) [m] from the vehicle's
    ground point at ``time_s`` [s]: amp * exp(-(r/R)^2) * (push * radial + flutter * tangent),
    push = 0.5 + 0.5 sin(2 pi (4 Hz t - r / 0.5 m)), flutter = 0.3 sin(2 pi 6.8 Hz t + 9 rx +
    7 ry) [1/m]."""
    r = math.sqrt(rx * rx + ry * ry)
    ux, uy = rx / max(r, 1e-6), ry / max(r, 1e-6)
    envelope = amp_m * math.exp(-((r / radius_m) ** 2))
    push = 0.5 + 0.5 * math.sin(2.0 * math.pi * (_WAVE_HZ * time_s - r / _WAVE_M))
    flutter = 0.3 * math.sin(2.0 * math.pi * _FLUTTER_HZ * time_s + 9.0 * rx + 7.0 * ry)
    return envelope * (push * ux - flutter * uy), envelope * (push * uy + flutter * ux)


@nb.njit(**_JIT)
def downwash_offsets(points_world, vehicle_world, time_s, amp_m, radius_m):
    """Displacements (N, 3) [m] (z = 0) of the grass at points (N, 3) NED by a vehicle at
    vehicle_world (3,) at ``time_s`` [s] (downwash_xy)."""
    out = np.zeros_like(points_world)
    for i in range(points_world.shape[0]):
        dx, dy = downwash_xy(
            points_world[i, 0] - vehicle_world[0],
            points_world[i, 1] - vehicle_world[1],
            time_s,
            amp_m,
            radius_m,
        )
        out[i, 0] = dx
        out[i, 1] = dy
    return out


@nb.njit(inline="always", **_JIT)
def _apply(T, x, y, z):
    """T (4, 4) applied to the point (x, y, z)."""
    return (
        T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3],
        T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3],
        T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3],
    )


@nb.njit(inline="always", **_JIT)
def _world_point(depth, rays_cam, i, T):
    """World point (x, y, z) NED [m] of pixel i: T (ray * depth / ray_z)."""
    s = depth[i] / rays_cam[i, 2]
    return _apply(T, rays_cam[i, 0] * s, rays_cam[i, 1] * s, rays_cam[i, 2] * s)


@nb.njit(**_JIT)
def downwash_sources(
    depth,
    rays_cam,
    T_world_cam,
    T_cam_world,
    hmap,
    inv_res,
    hx0,
    hy0,
    lens,
    vehicle,
    time_s,
    downwash,
    uv,
):
    """The pixels whose grass the downwash moves and where they now look, for cv2.remap.

    Ground pixels within 3 radii of the vehicle's ground point; each samples the frame at the
    projection of P - D(P, t) through the lens (9,) fx, fy, cx, cy, k1, k2, p1, p2, k3.
    depth (H*W,) [m], rays_cam (H*W, 3), T_world_cam (4, 4) and its inverse, the height field
    as apply_effects, vehicle (3,) [m], downwash (2,) amplitude and radius [m]. Writes uv[:n]
    (H*W, 2) [px] and returns the pixels' indices (n,) in increasing order.
    """
    n_px = depth.shape[0]
    idx = np.empty(n_px, dtype=np.int64)
    n = 0
    T = T_world_cam
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = (
        lens[0], lens[1], lens[2], lens[3], lens[4], lens[5], lens[6], lens[7], lens[8]
    )  # fmt: skip
    amp_m, radius_m = downwash[0], downwash[1]
    for i in range(n_px):
        if not math.isfinite(depth[i]):
            continue
        wx, wy, wz = _world_point(depth, rays_cam, i, T)
        h, _, _ = _height(hmap, inv_res, hx0, hy0, wx, wy)
        rx, ry = wx - vehicle[0], wy - vehicle[1]
        if abs(wz + h) >= _ON_GROUND_M or math.sqrt(rx * rx + ry * ry) >= 3.0 * radius_m:
            continue
        ox, oy = downwash_xy(rx, ry, time_s, amp_m, radius_m)
        # the source point P - D in the camera: T_cam_world (P - D)
        qx, qy, qz = _apply(T_cam_world, wx - ox, wy - oy, wz)
        u = v = math.nan
        if qz > 1e-6:
            x, y = qx / qz, qy / qz
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            u, v = fx * xd + cx, fy * yd + cy
        uv[n, 0] = u
        uv[n, 1] = v
        idx[n] = i
        n += 1
    return idx[:n]


@nb.njit(**_JIT)
def apply_effects(
    image,
    depth,
    rays_cam,
    T_world_cam,
    hmap,
    inv_res,
    hx0,
    hy0,
    moved,
    moved_bgr,
    vehicle,
    shadow,
    sun_ned,
    spec_grid,
    spec,
    out,
):
    """The ground's effects on every pixel; the 8-bit result into out (H*W, 3).

    image (H*W, 3) uint8 the rendered frame; depth (H*W,) z-depth [m] (inf: sky); rays_cam
    (H*W, 3) the pixels' rays; T_world_cam (4, 4); the height field ``hmap`` (rows y, columns
    x), 1 / its resolution [1/m], its origin (hx0, hy0) [m]; moved (n,) increasing pixel
    indices the downwash resampled and moved_bgr (n, 3) uint8 what they show now; vehicle (3,)
    NED [m]; shadow (2,) on (0/1) and the vehicle's radius [m]; sun_ned (3,) towards the sun;
    spec_grid (n, n) float32 water weights (0 x 0: no water) and spec (4,) the grid's origin
    [m], 1 / its cell [1/m], the highlight's strength and exponent.
    """
    T = T_world_cam
    shadow_on, shadow_r = shadow[0] > 0.0, shadow[1]
    # the sun's mirror direction about the level water's up normal (0, 0, -1)
    mx, my, mz = -sun_ned[0], -sun_ned[1], sun_ned[2]
    n_spec = spec_grid.shape[0]
    spec_x0, spec_inv, strength, exponent = spec[0], spec[1], spec[2], spec[3]
    px = np.empty(3)
    k = 0
    for i in range(image.shape[0]):
        if k < moved.shape[0] and moved[k] == i:
            for c in range(3):
                px[c] = moved_bgr[k, c]
            k += 1
        else:
            for c in range(3):
                px[c] = image[i, c]
        if math.isfinite(depth[i]):
            wx, wy, wz = _world_point(depth, rays_cam, i, T)
            if shadow_on:
                # the distance of the ray from P towards the sun to the vehicle's centre
                qx, qy, qz = vehicle[0] - wx, vehicle[1] - wy, vehicle[2] - wz
                along = qx * sun_ned[0] + qy * sun_ned[1] + qz * sun_ned[2]
                ex = qx - along * sun_ned[0]
                ey = qy - along * sun_ned[1]
                ez = qz - along * sun_ned[2]
                dist = math.sqrt(ex * ex + ey * ey + ez * ez)
                soft = 0.08 + 0.01 * max(along, 0.0)
                t = min(max((shadow_r + soft - dist) / (2.0 * soft), 0.0), 1.0)
                if along > 0.0:
                    light = 1.0 - SHADOW_DEPTH * (t * t * (3.0 - 2.0 * t))
                    for c in range(3):
                        px[c] *= light
            if n_spec > 0:
                h, _, _ = _height(hmap, inv_res, hx0, hy0, wx, wy)
                if abs(wz + h) < _ON_GROUND_M:
                    fxs = min(max((wx - spec_x0) * spec_inv - 0.5, 0.0), n_spec - 1.000001)
                    fys = min(max((wy - spec_x0) * spec_inv - 0.5, 0.0), n_spec - 1.000001)
                    ix, iy = int(fxs), int(fys)
                    ax, ay = fxs - ix, fys - iy
                    top = spec_grid[iy, ix] * (1 - ax) + spec_grid[iy, ix + 1] * ax
                    bottom = spec_grid[iy + 1, ix] * (1 - ax) + spec_grid[iy + 1, ix + 1] * ax
                    wgt = top * (1 - ay) + bottom * ay
                    if wgt > 0.0:
                        vx, vy, vz = T[0, 3] - wx, T[1, 3] - wy, T[2, 3] - wz
                        vn = math.sqrt(vx * vx + vy * vy + vz * vz)
                        glint = max(vx / vn * mx + vy / vn * my + vz / vn * mz, 0.0) ** exponent
                        for c in range(3):
                            water = 0.06 * SKY_BGR[c] + 255.0 * strength * glint
                            px[c] = px[c] * (1.0 - 0.6 * wgt) + wgt * water
        for c in range(3):
            out[i, c] = min(max(math.floor(px[c] + 0.5), 0.0), 255.0)
