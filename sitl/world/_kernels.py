"""Compiled (numba) inner loops of the simulator: exact ray casting, texturing, noise.

World frame local NED (x north, y east, z down); terrain height h is positive *up*, so the
ground surface is z = -h(x, y). The ground is the bilinear interpolant of a height grid
``hmap[iy, ix]`` at x = x0 + ix * res, y = y0 + iy * res (clamped beyond the grid). Buildings are
axis-aligned boxes ``boxes[k] = (xmin, xmax, ymin, ymax, h_bottom, h_top)``.

Ray casting is exact to ~1e-6 m: safe (Lipschitz-bounded) steps approach the first intersection
with the height field from above without ever passing it, Newton steps finish it; boxes use the
slab test. A uniform grid of box indices (CSR) limits the boxes tested per ray.

Hit kinds: -1 miss, 0 ground, 1 roof, 2 wall.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

# fastmath without nnan/ninf: infinities mark misses. Compiled code is deterministic, so the
# same seed still gives bit-identical images on one machine.
_JIT = {
    "cache": True,
    "nogil": True,
    "error_model": "numpy",
    "fastmath": {"nsz", "arcp", "contract", "afn", "reassoc"},
}

MISS, GROUND, ROOF, WALL = -1, 0, 1, 2


@nb.njit(inline="always", **_JIT)
def _height(hmap, inv_res, x0, y0, x, y):
    """Bilinear height and its gradient (h, dh/dx, dh/dy) at (x, y)."""
    ny, nx = hmap.shape
    fx = (x - x0) * inv_res
    fy = (y - y0) * inv_res
    gx = 1.0
    gy = 1.0
    if fx < 0.0:
        fx = 0.0
        gx = 0.0
    elif fx > nx - 1.000001:
        fx = nx - 1.000001
        gx = 0.0
    if fy < 0.0:
        fy = 0.0
        gy = 0.0
    elif fy > ny - 1.000001:
        fy = ny - 1.000001
        gy = 0.0
    ix = int(fx)
    iy = int(fy)
    ax = fx - ix
    ay = fy - iy
    h00 = hmap[iy, ix]
    h01 = hmap[iy, ix + 1]
    h10 = hmap[iy + 1, ix]
    h11 = hmap[iy + 1, ix + 1]
    h = (h00 * (1.0 - ax) + h01 * ax) * (1.0 - ay) + (h10 * (1.0 - ax) + h11 * ax) * ay
    hx = ((h01 - h00) * (1.0 - ay) + (h11 - h10) * ay) * inv_res * gx
    hy = ((h10 - h00) * (1.0 - ax) + (h11 - h01) * ax) * inv_res * gy
    return h, hx, hy


@nb.njit(**_JIT)
def height_at(hmap, inv_res, x0, y0, xs, ys):
    """Terrain height (N,) [m, up] at points xs, ys (N,) [m]."""
    out = np.empty(xs.shape[0])
    for i in range(xs.shape[0]):
        h, _, _ = _height(hmap, inv_res, x0, y0, xs[i], ys[i])
        out[i] = h
    return out


@nb.njit(inline="always", **_JIT)
def _cast_ground(ox, oy, oz, dx, dy, dz, ground, t_guess):
    """First height-field hit along a unit ray: (t, dh/dx, dh/dy) there, t = inf on a miss.

    ``blocks[by, bx] = (max height, Lipschitz x, Lipschitz y)`` hold, for every block of the
    height grid, bounds valid within ``b_reach`` metres horizontally of any point of the block.
    A step that stays within that reach is safe when it descends no lower than the local
    maximum height, or no further than gap / (dz + Lx |dx| + Ly |dy|) (the terrain cannot rise
    faster along the ray); steps approach the first hit from above, Newton's method ends it.
    When the global slope bounds (lip_x, lip_y) prove the hit unique, a bracketed Newton
    iteration from ``t_guess`` (the neighbouring pixel's distance) replaces the stepping.

    ``ground`` = (hmap, inv_res, x0, y0, hmin, hmax, plane, lip_x, lip_y, blocks, b_inv,
    b_reach, tmax): the height grid [m, up] and its origin [m] and 1 / resolution [1/m], its
    height range [m], the plane (a, b, c, flag) when it is one, the global slope bounds, the
    blocks with 1 / block size [1/m] and their reach [m], the longest ray [m].
    """
    hmap, inv_res, x0, y0, hmin, hmax, plane, lip_x, lip_y, blocks, b_inv, b_reach, tmax = ground
    if plane[3] > 0.0:
        # the terrain is the plane h = a + b x + c y: closed form
        denom = dz + plane[1] * dx + plane[2] * dy
        if denom <= 1e-12:
            return math.inf, 0.0, 0.0
        t = (-oz - plane[0] - plane[1] * ox - plane[2] * oy) / denom
        if t < 0.0:
            return math.inf, 0.0, 0.0
        return t, plane[1], plane[2]
    nby = blocks.shape[0]
    nbx = blocks.shape[1]
    dxy = math.sqrt(dx * dx + dy * dy)
    t = 0.0
    if -oz > hmax:
        if dz <= 0.0:
            return math.inf, 0.0, 0.0
        t = (-oz - hmax) / dz
    if dz > lip_x * abs(dx) + lip_y * abs(dy) and t_guess > 0.0 and -oz > hmin:
        # The gap g(t) = ray height - terrain height strictly decreases along this ray (the
        # terrain cannot rise as fast as the ray descends), so it has exactly one root in
        # [t, t_hi]: bracketed Newton from the neighbouring pixel's distance finds it.
        t_lo = t
        t_hi = (-oz - hmin) / dz
        tt = min(max(t_guess, t_lo), t_hi)
        for _ in range(40):
            h, hx, hy = _height(hmap, inv_res, x0, y0, ox + tt * dx, oy + tt * dy)
            g = -(oz + tt * dz) - h
            if g > 0.0:
                t_lo = tt
            else:
                t_hi = tt
            if abs(g) < 5e-7:
                return tt, hx, hy
            dg = -dz - (hx * dx + hy * dy)
            step = -g / dg
            nxt = tt + step
            if abs(step) < 1e-4 and t_lo <= nxt <= t_hi:
                # one Newton step this short is exact to ~1e-7 m: the bilinear surface's
                # curvature along the ray is tiny and a cell edge can bend it by < 1e-3 * step
                return nxt, hx, hy
            if not (t_lo < nxt < t_hi):
                nxt = 0.5 * (t_lo + t_hi)
            if t_hi - t_lo < 1e-10:
                return nxt, hx, hy
            tt = nxt
        return tt, hx, hy
    t_reach = b_reach / dxy if dxy > 1e-12 else math.inf
    g = 0.0
    hx = 0.0
    hy = 0.0
    for _ in range(600):
        px = ox + t * dx
        py = oy + t * dy
        h, hx, hy = _height(hmap, inv_res, x0, y0, px, py)
        hr = -(oz + t * dz)
        g = hr - h
        if g < 0.02:
            break
        bx = min(max(int((px - x0) * b_inv), 0), nbx - 1)
        by = min(max(int((py - y0) * b_inv), 0), nby - 1)
        denom = dz + blocks[by, bx, 1] * abs(dx) + blocks[by, bx, 2] * abs(dy)
        step = g / denom if denom > 1e-12 else math.inf
        if dz > 0.0:
            step = max(step, (hr - blocks[by, bx, 0]) / dz)
        step = min(step, t_reach)
        t += step
        if t > tmax:
            return math.inf, 0.0, 0.0
    if g < -1e-9 and t == 0.0:
        return 0.0, hx, hy  # origin under the ground
    for _ in range(8):
        dg = -dz - (hx * dx + hy * dy)
        if abs(g) < 1e-9 or dg >= -1e-12:
            break
        t -= g / dg
        h, hx, hy = _height(hmap, inv_res, x0, y0, ox + t * dx, oy + t * dy)
        g = -(oz + t * dz) - h
    return t, hx, hy


@nb.njit(inline="always", **_JIT)
def _cast_boxes(ox, oy, oz, dx, dy, dz, t_best, box_geo):
    """First box hit before t_best: (t, box index or -1, face axis 0/1/2, face sign).

    ``box_geo`` = (boxes, box_top, cell_start, cell_boxes, g_x0, g_y0, g_inv, g_nx, g_ny): the
    boxes (K, 6), the highest roof [m, up], the CSR grid of box indices (cell starts, indices),
    its origin [m], 1 / cell size [1/m] and size in cells.
    """
    boxes, box_top, cell_start, cell_boxes, g_x0, g_y0, g_inv, g_nx, g_ny = box_geo
    hit_box = -1
    axis = 0
    sign = 0.0
    if boxes.shape[0] == 0:
        return t_best, hit_box, axis, sign
    # the part of the ray below the highest roof and before t_best
    ta = 0.0
    if -oz > box_top:
        if dz <= 0.0:
            return t_best, hit_box, axis, sign
        ta = (-oz - box_top) / dz
    tb = t_best
    if tb > 1e6:
        tb = ta + 1000.0
    if ta > tb:
        return t_best, hit_box, axis, sign
    xa = ox + ta * dx
    xb = ox + tb * dx
    ya = oy + ta * dy
    yb = oy + tb * dy
    cx0 = int(math.floor((min(xa, xb) - g_x0) * g_inv))
    cx1 = int(math.floor((max(xa, xb) - g_x0) * g_inv))
    cy0 = int(math.floor((min(ya, yb) - g_y0) * g_inv))
    cy1 = int(math.floor((max(ya, yb) - g_y0) * g_inv))
    cx0 = max(cx0, 0)
    cy0 = max(cy0, 0)
    cx1 = min(cx1, g_nx - 1)
    cy1 = min(cy1, g_ny - 1)
    inv_x = 1.0 / dx
    inv_y = 1.0 / dy
    inv_z = 1.0 / dz
    for cy in range(cy0, cy1 + 1):
        for cx in range(cx0, cx1 + 1):
            c = cy * g_nx + cx
            for j in range(cell_start[c], cell_start[c + 1]):
                k = cell_boxes[j]
                t1 = (boxes[k, 0] - ox) * inv_x
                t2 = (boxes[k, 1] - ox) * inv_x
                t3 = (boxes[k, 2] - oy) * inv_y
                t4 = (boxes[k, 3] - oy) * inv_y
                t5 = (-boxes[k, 5] - oz) * inv_z  # z of the roof
                t6 = (-boxes[k, 4] - oz) * inv_z  # z of the bottom
                nx_ = min(t1, t2)
                ny_ = min(t3, t4)
                nz_ = min(t5, t6)
                tnear = max(nx_, max(ny_, nz_))
                tfar = min(max(t1, t2), min(max(t3, t4), max(t5, t6)))
                if tnear <= tfar and tnear >= 0.0 and tnear < t_best:
                    t_best = tnear
                    hit_box = k
                    if tnear == nz_:
                        axis = 2
                        sign = -1.0 if dz > 0.0 else 1.0
                    elif tnear == nx_:
                        axis = 0
                        sign = -1.0 if dx > 0.0 else 1.0
                    else:
                        axis = 1
                        sign = -1.0 if dy > 0.0 else 1.0
    return t_best, hit_box, axis, sign


@nb.njit(inline="always", **_JIT)
def _cast(ox, oy, oz, dx, dy, dz, geo, t_guess):
    """First hit of a unit ray on the ground or a building, from the packed geometry
    ``geo = (ground, box_geo)`` (World.kernel_geometry): (t, t of the ground alone, dh/dx,
    dh/dy, box, face axis, sign)."""
    ground, box_geo = geo
    t_ground, hx, hy = _cast_ground(ox, oy, oz, dx, dy, dz, ground, t_guess)
    t, k, axis, sign = _cast_boxes(ox, oy, oz, dx, dy, dz, t_ground, box_geo)
    return t, t_ground, hx, hy, k, axis, sign


@nb.njit(**_JIT)
def cast_rays(
    origins,
    dirs,
    geo,
):
    """Cast unit rays (N, 3) from origins (N, 3): t (N,), normals (N, 3), kind (N,), box (N,)."""
    n = origins.shape[0]
    t_out = np.empty(n)
    normals = np.zeros((n, 3))
    kind = np.full(n, MISS, dtype=np.int64)
    box_out = np.full(n, -1, dtype=np.int64)
    t_guess = 0.0
    for i in range(n):
        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        t, t_ground, hx, hy, k, axis, sign = _cast(ox, oy, oz, dx, dy, dz, geo, t_guess)
        if t_ground < math.inf:
            t_guess = t_ground
        t_out[i] = t
        if k >= 0:
            box_out[i] = k
            normals[i, axis] = sign
            kind[i] = ROOF if axis == 2 else WALL
        elif t < math.inf:
            s = 1.0 / math.sqrt(hx * hx + hy * hy + 1.0)
            normals[i, 0] = -hx * s
            normals[i, 1] = -hy * s
            normals[i, 2] = -s
            kind[i] = GROUND
    return t_out, normals, kind, box_out


_WRAP_OFFSET = float(1 << 24)  # a multiple of every texture size: makes coordinates positive
_LEVEL_SCALE = np.array([2.0**-level for level in range(32)])  # texel scale of mip level l


@nb.njit(inline="always", **_JIT)
def _tex_trilinear(data, offs, sizes, tex, u0, v0, lod):
    """Mip-mapped (trilinear) lookup of texture ``tex`` at level-0 texel coords and ``lod``.

    Each level l is stored as interleaved pairs (level l, level l+1 resampled to level l's
    grid), so one wrapped bilinear fetch of two channels gives both levels.
    """
    nlev = sizes.shape[1]
    if lod < 0.0:
        lod = 0.0
    if lod > nlev - 1.0:
        lod = nlev - 1.0
    l0 = int(lod)
    a = lod - l0
    n = sizes[tex, l0]
    s = _LEVEL_SCALE[l0]
    u = u0 * s + (_WRAP_OFFSET - 0.5)
    v = v0 * s + (_WRAP_OFFSET - 0.5)
    iu0 = int(u)
    iv0 = int(v)
    au = u - iu0
    av = v - iv0
    m = n - 1
    iu = (iu0 & m) * 2
    iu1 = ((iu0 + 1) & m) * 2
    off = offs[tex, l0]
    row0 = off + (iv0 & m) * n * 2
    row1 = off + ((iv0 + 1) & m) * n * 2
    w00 = (1.0 - au) * (1.0 - av)
    w01 = au * (1.0 - av)
    w10 = (1.0 - au) * av
    w11 = au * av
    c0 = (
        data[row0 + iu] * w00
        + data[row0 + iu1] * w01
        + data[row1 + iu] * w10
        + data[row1 + iu1] * w11
    )
    c1 = (
        data[row0 + iu + 1] * w00
        + data[row0 + iu1 + 1] * w01
        + data[row1 + iu + 1] * w10
        + data[row1 + iu1 + 1] * w11
    )
    return c0 + (c1 - c0) * a


@nb.njit(inline="always", **_JIT)
def _field(fields, f_x0, f_y0, f_inv, x, y):
    """Bilinear lookup of the four packed low-frequency fields (Ny, Nx, 4) at (x, y)."""
    ny, nx, _ = fields.shape
    fx = min(max((x - f_x0) * f_inv, 0.0), nx - 1.000001)
    fy = min(max((y - f_y0) * f_inv, 0.0), ny - 1.000001)
    ix = int(fx)
    iy = int(fy)
    ax = fx - ix
    ay = fy - iy
    w00 = (1.0 - ax) * (1.0 - ay)
    w01 = ax * (1.0 - ay)
    w10 = (1.0 - ax) * ay
    w11 = ax * ay
    a = fields[iy, ix]
    b = fields[iy, ix + 1]
    c = fields[iy + 1, ix]
    d = fields[iy + 1, ix + 1]
    return (
        a[0] * w00 + b[0] * w01 + c[0] * w10 + d[0] * w11,
        a[1] * w00 + b[1] * w01 + c[1] * w10 + d[1] * w11,
        a[2] * w00 + b[2] * w01 + c[2] * w10 + d[2] * w11,
        a[3] * w00 + b[3] * w01 + c[3] * w10 + d[3] * w11,
    )


@nb.njit(inline="always", **_JIT)
def _quantise(value, noise):
    """8-bit level of a linear value plus noise, rounded and clipped."""
    v = math.floor(value + noise + 0.5)
    if v < 0.0:
        v = 0.0
    elif v > 255.0:
        v = 255.0
    return np.uint8(v)


@nb.njit(**_JIT)
def render(
    R_rows,
    p_rows,
    rays_cam,
    width,
    focal_px,
    geo,
    tex_data,
    tex_offs,
    tex_sizes,
    layers,
    fields,
    f_x0,
    f_y0,
    f_inv,
    box_tint,
    sun_ned,
    ambient,
    out_bgr,
    out_depth,
    noise_bank,
    noise_start,
    sigma_dn,
    out_u8,
):
    """Ray cast and shade every pixel; z-depth (H*W,) [m] into out_depth.

    With an empty ``out_u8`` the linear BGR values go to out_bgr (H*W, 3) float32 (for motion
    blur and laser marks); otherwise noise from the bank (from ``noise_start``) is added and the
    8-bit image written to out_u8 (H*W, 3) directly.

    R_rows (H, 3, 3), p_rows (H, 3): the camera pose T_world_cam of each image row (all equal
    for a global shutter; a rolling shutter's rows each at their own time: rolling_shutter.py).
    z-depth is in the camera frame of the pixel's own row.

    rays_cam: (H*W, 3) unit rays in the camera frame. layers: (4, 11) texture layers (ground A,
    ground B, roof, wall): tex, tile_m, cos, sin, off_u, off_v, tint b g r, texels per metre,
    log2(texels per metre) -- see terrain.py.
    """
    n = rays_cam.shape[0]
    sun_norm = -sun_ned[2]
    final = out_u8.shape[0] > 0
    nb_len = noise_bank.shape[0]
    j = noise_start
    # Warm starts come from the same column of the rows above (quadratic extrapolation), so
    # pixels of one row do not wait for each other and the CPU overlaps their iterations.
    rows = np.zeros((3, width))
    t_prev = 0.0
    for i in range(n):
        col = i % width
        row = i // width
        r_a = rows[(row - 1) % 3, col] if row >= 1 else 0.0
        r_b = rows[(row - 2) % 3, col] if row >= 2 else 0.0
        r_c = rows[(row - 3) % 3, col] if row >= 3 else 0.0
        rx, ry, rz = rays_cam[i, 0], rays_cam[i, 1], rays_cam[i, 2]
        ox, oy, oz = p_rows[row, 0], p_rows[row, 1], p_rows[row, 2]
        R = R_rows[row]
        dx = R[0, 0] * rx + R[0, 1] * ry + R[0, 2] * rz
        dy = R[1, 0] * rx + R[1, 1] * ry + R[1, 2] * rz
        dz = R[2, 0] * rx + R[2, 1] * ry + R[2, 2] * rz
        if r_c > 0.0 and r_b > 0.0 and r_a > 0.0:
            t_guess = 3.0 * (r_a - r_b) + r_c
        elif r_b > 0.0 and r_a > 0.0:
            t_guess = 2.0 * r_a - r_b
        elif r_a > 0.0:
            t_guess = r_a
        else:
            t_guess = t_prev
        t, t_ground, hx, hy, k, axis, sign = _cast(ox, oy, oz, dx, dy, dz, geo, t_guess)
        rows[row % 3, col] = t_ground if t_ground < math.inf else 0.0
        if t_ground < math.inf:
            t_prev = t_ground
        if t == math.inf:
            b = 200.0
            g = 170.0
            r = 150.0
            if final:
                if j + 3 > nb_len:
                    j = 0
                out_u8[i, 0] = _quantise(b, sigma_dn * noise_bank[j])
                out_u8[i, 1] = _quantise(g, sigma_dn * noise_bank[j + 1])
                out_u8[i, 2] = _quantise(r, sigma_dn * noise_bank[j + 2])
                j += 3
            else:
                out_bgr[i, 0] = b
                out_bgr[i, 1] = g
                out_bgr[i, 2] = r
            out_depth[i] = math.inf
            continue
        out_depth[i] = t * rz
        px = ox + t * dx
        py = oy + t * dy
        pz = oz + t * dz
        w_b, albedo, warp_u, warp_v = _field(fields, f_x0, f_y0, f_inv, px, py)
        if k < 0:
            s = 1.0 / math.sqrt(hx * hx + hy * hy + 1.0)
            nx_ = -hx * s
            ny_ = -hy * s
            nz_ = -s
        else:
            nx_ = 0.0
            ny_ = 0.0
            nz_ = 0.0
            if axis == 0:
                nx_ = sign
            elif axis == 1:
                ny_ = sign
            else:
                nz_ = sign
        cos_inc = -(nx_ * dx + ny_ * dy + nz_ * dz)
        if cos_inc < 0.2:
            cos_inc = 0.2
        log_footprint = math.log2(t * rz * rz / (focal_px * cos_inc))
        lam = nx_ * sun_ned[0] + ny_ * sun_ned[1] + nz_ * sun_ned[2]
        if lam < 0.0:
            lam = 0.0
        shade = ambient + (1.0 - ambient) * lam / sun_norm
        b = 0.0
        g = 0.0
        r = 0.0
        if k < 0:
            # ground: two photo layers mixed by a low-frequency weight, domain-warped coordinates
            wu = px + warp_u
            wv = py + warp_v
            for li in range(2):
                w = w_b if li == 1 else 1.0 - w_b
                if w < 0.02:
                    continue
                tex = int(layers[li, 0])
                scale = layers[li, 9]
                u = (layers[li, 2] * wu + layers[li, 3] * wv) * scale + layers[li, 4]
                v = (-layers[li, 3] * wu + layers[li, 2] * wv) * scale + layers[li, 5]
                lod = log_footprint + layers[li, 10]
                val = _tex_trilinear(tex_data, tex_offs, tex_sizes, tex, u, v, lod) * w
                b += val * layers[li, 6]
                g += val * layers[li, 7]
                r += val * layers[li, 8]
        else:
            li = 2 if axis == 2 else 3
            tex = int(layers[li, 0])
            scale = layers[li, 9]
            if axis == 2:
                u = px * scale + layers[li, 4]
                v = py * scale + layers[li, 5]
            elif axis == 0:
                u = py * scale + layers[li, 4] + k * 97.0
                v = pz * scale
            else:
                u = px * scale + layers[li, 4] + k * 97.0
                v = pz * scale
            lod = log_footprint + layers[li, 10]
            val = _tex_trilinear(tex_data, tex_offs, tex_sizes, tex, u, v, lod)
            b = val * layers[li, 6] * box_tint[k, 0]
            g = val * layers[li, 7] * box_tint[k, 1]
            r = val * layers[li, 8] * box_tint[k, 2]
        f = 2.0 * albedo * shade
        if final:
            if j + 3 > nb_len:
                j = 0
            out_u8[i, 0] = _quantise(b * f, sigma_dn * noise_bank[j])
            out_u8[i, 1] = _quantise(g * f, sigma_dn * noise_bank[j + 1])
            out_u8[i, 2] = _quantise(r * f, sigma_dn * noise_bank[j + 2])
            j += 3
        else:
            out_bgr[i, 0] = b * f
            out_bgr[i, 1] = g * f
            out_bgr[i, 2] = r * f


@nb.njit(**_JIT)
def finish(linear_bgr, noise_bank, start, sigma_dn, out_u8):
    """Add Gaussian noise from a bank of N(0,1) samples (from ``start``) and quantise.

    Draws the bank exactly as :func:`render` does when it writes 8-bit output directly.
    """
    n = linear_bgr.shape[0]
    nb_len = noise_bank.shape[0]
    j = start
    for i in range(n):
        if j + 3 > nb_len:
            j = 0
        for c in range(3):
            out_u8[i, c] = _quantise(linear_bgr[i, c], sigma_dn * noise_bank[j + c])
        j += 3
