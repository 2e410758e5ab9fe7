"""Seeded terrains for the simulator, with exact ray casting and photo textures.

Terrains (issue 2):
- ``flat``: level ground at h = 0.
- ``hills``: smooth irregular ground with a few metres of relief on a 5 cm height grid.
- ``urban``: level ground with axis-aligned box buildings 1-8 m tall (sharp 3D structure,
  occlusions) and a clear area of 8 m radius around the origin for take-off.
- ``slope``: a plane tilted by 10-15 degrees (seeded direction and angle).

Frames: local NED; heights ``h`` are positive up, the ground surface is z = -h(x, y) and
h(0, 0) = 0. Textures are the CC0 photographs shipped in scikit-image (grass, gravel, brick),
mip-mapped, mixed by low-frequency seeded fields and domain-warped so that no tile repeats
visibly. Any terrain may instead be covered by a hard ground (``GroundOptions.surface``:
repeating or low-texture, surfaces.py) and carry water-like specular patches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from companion.errors import SitlError
from companion.sitl.world import _kernels
from companion.sitl.world.surfaces import SpecularPatches, surface_ground
from companion.sitl_options import GroundOptions
from companion.types import F64

F32 = NDArray[np.float32]
I64 = NDArray[np.int64]

TERRAINS = ("flat", "hills", "urban", "slope")
_BOX_CELL_M = 4.0
_FIELD_RES_M = 0.5
_TEXTURE_SIZE = 512  # side of the photo textures [texels]
_BLOCK_M = 1.0  # block size of the ray-stepping bounds [m]
_BLOCK_REACH = 2  # blocks of dilation: bounds hold within 2 m of a block

# texture ids in the atlas
TEX_GRASS, TEX_GRAVEL, TEX_BRICK = 0, 1, 2


@dataclass(frozen=True, slots=True)
class RayHits:
    """Result of casting N rays.

    t_m: (N,) distance along each unit ray [m] (inf = miss); points_world: (N, 3) hit points
    (NED) [m]; normals_world: (N, 3) outward unit normals; kind: (N,) -1 miss, 0 ground, 1 roof,
    2 wall; box_id: (N,) building index or -1.
    """

    t_m: F64
    points_world: F64
    normals_world: F64
    kind: I64
    box_id: I64


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_cells: float) -> F64:
    """Zero-mean, unit-std Gaussian-filtered white noise (wrap-free: reflect boundary)."""
    n = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_cells, mode="reflect")
    n = n - n.mean()
    return np.asarray(n / (n.std() + 1e-12), dtype=np.float64)


def _photo(name: str) -> F32:
    """A scikit-image CC0 photo as float32 in [0, 1], contrast-normalised to mean 0.5."""
    import skimage.data

    img = np.asarray(getattr(skimage.data, name)(), dtype=np.float64)
    if img.ndim == 3:
        img = img.mean(axis=2)
    # remove the photo's own low-frequency shading so tiles join without visible seams
    low = ndimage.gaussian_filter(img, 24.0, mode="wrap")
    img = img - low
    img = 0.5 + 0.19 * img / (img.std() + 1e-9)
    out: F32 = np.clip(img, 0.02, 0.98).astype(np.float32)
    return out


def _upsample2_wrap(img: F32) -> F32:
    """Bilinear 2x upsampling with wrap-around, texel centres aligned (n, n) -> (2n, 2n)."""
    out = img.astype(np.float64)
    for axis in (0, 1):
        prev = np.roll(out, 1, axis=axis)
        nxt = np.roll(out, -1, axis=axis)
        even = 0.75 * out + 0.25 * prev
        odd = 0.75 * out + 0.25 * nxt
        shape = list(out.shape)
        shape[axis] *= 2
        both = np.empty(shape)
        idx = [slice(None)] * 2
        idx[axis] = slice(0, None, 2)
        both[tuple(idx)] = even
        idx[axis] = slice(1, None, 2)
        both[tuple(idx)] = odd
        out = both
    return out.astype(np.float32)


def _pyramid_atlas(textures: list[F32]) -> tuple[F32, I64, I64]:
    """Mip pyramids of square power-of-two textures, flattened: data, offsets (T, L), sizes.

    Level l of a texture is stored as interleaved pairs (level l, level l+1 upsampled to level
    l's grid), so a trilinear lookup is a single two-channel bilinear fetch.
    """
    n0 = textures[0].shape[0]
    levels = int(math.log2(n0)) + 1
    chunks: list[F32] = []
    offs = np.zeros((len(textures), levels), dtype=np.int64)
    sizes = np.zeros((len(textures), levels), dtype=np.int64)
    pos = 0
    for ti, tex in enumerate(textures):
        if tex.shape != (n0, n0):
            raise SitlError("textures must be square, power-of-two and of one size")
        pyramid = [tex.astype(np.float32)]
        while pyramid[-1].shape[0] > 1:
            lv = pyramid[-1]
            pyramid.append(
                0.25 * (lv[0::2, 0::2] + lv[1::2, 0::2] + lv[0::2, 1::2] + lv[1::2, 1::2])
            )
        for li, level in enumerate(pyramid):
            coarser = _upsample2_wrap(pyramid[li + 1]) if li + 1 < levels else level
            pair = np.stack([level, coarser], axis=2).astype(np.float32)
            offs[ti, li] = pos
            sizes[ti, li] = level.shape[0]
            chunks.append(pair.ravel())
            pos += pair.size
    return np.concatenate(chunks).astype(np.float32), offs, sizes


class World:
    """A terrain: height grid, buildings, textures and the ray-casting query.

    Build it with :func:`make_world`. All public arrays are float64 NED metres.
    """

    fields: F64  # (Ny, Nx, 4) the ground's mix weight, albedo and warp on a 0.5 m grid
    layers: F64  # (4, 11) texture layers: ground A, ground B, roof, wall (_kernels.render)

    def __init__(
        self,
        name: str,
        seed: int,
        size_m: float,
        heights: F32,
        res_m: float,
        boxes: F64,
        default_altitude_m: float,
        ground: GroundOptions | None = None,
    ) -> None:
        self.name = name
        self.ground = ground or GroundOptions()
        self.seed = seed
        self.size_m = float(size_m)
        self.half_m = self.size_m / 2.0
        self.heights = np.ascontiguousarray(heights, dtype=np.float32)
        self.res_m = float(res_m)
        self.x0 = -self.half_m
        self.y0 = -self.half_m
        self.boxes = np.ascontiguousarray(boxes, dtype=np.float64).reshape(-1, 6)
        self.default_altitude_m = default_altitude_m
        self.h_min = float(self.heights.min())
        self.h_max = float(self.heights.max())
        h = self.heights[:2, :2].astype(np.float64)
        # a 2x2 grid with planar corners is exactly the plane h = a + b x + c y
        self.plane = np.zeros(4)
        if self.heights.shape == (2, 2) and abs(h[1, 1] - h[1, 0] - h[0, 1] + h[0, 0]) < 1e-9:
            b = (h[0, 1] - h[0, 0]) / self.res_m
            c = (h[1, 0] - h[0, 0]) / self.res_m
            self.plane = np.array([h[0, 0] - b * self.x0 - c * self.y0, b, c, 1.0])
        self.box_top = float(self.boxes[:, 5].max(initial=-1e9))
        self._build_blocks()
        self._build_box_grid()
        rng = np.random.default_rng([seed, 7])
        self.box_tint = np.clip(
            1.0
            + 0.12 * rng.standard_normal((len(self.boxes), 1))
            + 0.05 * rng.standard_normal((len(self.boxes), 3)),
            0.6,
            1.4,
        )
        self._build_fields(rng)
        self.surface_textures: list[F32] = []
        if self.ground.surface != "photo":
            shape = self.fields.shape[:2]
            self.surface_textures, rows, fields = surface_ground(
                self.ground.surface,
                seed,
                (shape[0], shape[1]),
                _FIELD_RES_M,
                self.ground.checker_m,
            )
            self.fields = np.ascontiguousarray(fields)
            self.layers[:2, :9] = rows
            self.layers[:2, 9] = _TEXTURE_SIZE / rows[:, 1]
            self.layers[:2, 10] = np.log2(self.layers[:2, 9])
        share = self.ground.specular_patches
        self.specular = SpecularPatches(seed, self.size_m, share) if share > 0 else None

    # ------------------------------------------------------------------ construction
    def _build_blocks(self) -> None:
        """Per-block bounds for safe ray stepping: (max height, Lipschitz x, Lipschitz y).

        The surface is sampled on a lattice of spacing s = min(res, block) whose lines contain
        every grid line and block edge, so lattice maxima and finite differences bound the
        bilinear surface exactly. Each block's bounds are then dilated by _BLOCK_REACH blocks,
        so they hold within _BLOCK_REACH * _BLOCK_M metres of any point in the block.
        """
        b = _BLOCK_M
        s = min(self.res_m, b)
        per = int(round(b / s))
        nb = int(math.ceil(self.size_m / b))
        n = nb * per + 1
        H: NDArray[np.floating]
        if s == self.res_m and self.heights.shape == (n, n):
            H = self.heights  # the lattice is the grid itself (float32)
        else:
            lattice = self.x0 + s * np.arange(n)
            X, Y = np.meshgrid(lattice, lattice)
            H = self.height(X.ravel(), Y.ravel()).reshape(n, n)  # rows: y, cols: x
        gx = np.abs(np.diff(H, axis=1)) / s  # (n, n-1)
        gy = np.abs(np.diff(H, axis=0)) / s  # (n-1, n)

        def per_block(a: NDArray[np.floating]) -> F64:
            a = a[: nb * per, : nb * per]
            return np.asarray(a.reshape(nb, per, nb, per).max(axis=(1, 3)), dtype=np.float64)

        hmax = np.maximum(per_block(H[:-1, :-1]), per_block(H[1:, 1:]))
        hmax = np.maximum(hmax, np.maximum(per_block(H[:-1, 1:]), per_block(H[1:, :-1])))
        lx = np.maximum(per_block(gx[:-1, :]), per_block(gx[1:, :]))
        ly = np.maximum(per_block(gy[:, :-1]), per_block(gy[:, 1:]))
        size = 2 * _BLOCK_REACH + 1
        stats = [ndimage.maximum_filter(a, size=size, mode="nearest") for a in (hmax, lx, ly)]
        self.blocks = np.ascontiguousarray(np.stack(stats, axis=2), dtype=np.float64)
        # a margin over float32 rounding keeps the bounds conservative
        self.blocks[..., 1:] = self.blocks[..., 1:] * 1.001 + 1e-6
        # global Lipschitz bounds of the bilinear interpolant along x and y
        self.lip_x = float(lx.max()) * 1.001 + 1e-6
        self.lip_y = float(ly.max()) * 1.001 + 1e-6
        self.b_inv = 1.0 / b
        self.b_reach = _BLOCK_REACH * b

    def _build_box_grid(self) -> None:
        n = max(1, int(math.ceil(self.size_m / _BOX_CELL_M)))
        self.g_nx = n
        self.g_ny = n
        self.g_inv = 1.0 / _BOX_CELL_M
        cells: list[list[int]] = [[] for _ in range(n * n)]
        for k, (xmin, xmax, ymin, ymax, _, _) in enumerate(self.boxes):
            cx0 = max(int(math.floor((xmin - self.x0) * self.g_inv)), 0)
            cx1 = min(int(math.floor((xmax - self.x0) * self.g_inv)), n - 1)
            cy0 = max(int(math.floor((ymin - self.y0) * self.g_inv)), 0)
            cy1 = min(int(math.floor((ymax - self.y0) * self.g_inv)), n - 1)
            for cy in range(cy0, cy1 + 1):
                for cx in range(cx0, cx1 + 1):
                    cells[cy * n + cx].append(k)
        self.cell_start = np.zeros(n * n + 1, dtype=np.int64)
        self.cell_start[1:] = np.cumsum([len(c) for c in cells])
        flat = [k for c in cells for k in c]
        self.cell_boxes = np.asarray(flat, dtype=np.int64)

    def _build_fields(self, rng: np.random.Generator) -> None:
        nf = int(round(self.size_m / _FIELD_RES_M)) + 1
        shape = (nf, nf)
        gravel = _smooth_noise(rng, shape, 7.0 / _FIELD_RES_M)
        # grass and gravel patches with ~1 m wide transitions (only there are both sampled)
        w_gravel = np.clip(0.25 + gravel, 0.0, 1.0)
        albedo = (
            1.0
            + 0.10 * _smooth_noise(rng, shape, 1.5 / _FIELD_RES_M)
            + 0.08 * _smooth_noise(rng, shape, 6.0 / _FIELD_RES_M)
        )
        warp_u = 0.6 * _smooth_noise(rng, shape, 4.0 / _FIELD_RES_M)
        warp_v = 0.6 * _smooth_noise(rng, shape, 4.0 / _FIELD_RES_M)
        self.fields = np.ascontiguousarray(
            np.stack([w_gravel, albedo, warp_u, warp_v], axis=2), dtype=np.float64
        )
        self.f_inv = 1.0 / _FIELD_RES_M
        # texture layers: tex, tile_m, cos, sin, off_u, off_v, tint b, g, r (8-bit levels)
        a1, a2 = rng.uniform(0, 2 * np.pi, 2)
        o = rng.uniform(0, 512, 4)
        self.layers = np.array(
            [
                [TEX_GRASS, 2.4, math.cos(a1), math.sin(a1), o[0], o[1], 62.0, 122.0, 88.0],
                [TEX_GRAVEL, 1.9, math.cos(a2), math.sin(a2), o[2], o[3], 112.0, 118.0, 127.0],
                [TEX_GRAVEL, 1.3, 1.0, 0.0, 0.0, 0.0, 100.0, 103.0, 108.0],
                [TEX_BRICK, 1.6, 1.0, 0.0, 0.0, 0.0, 72.0, 84.0, 138.0],
            ],
            dtype=np.float64,
        )
        texels_per_m = _TEXTURE_SIZE / self.layers[:, 1]
        self.layers = np.ascontiguousarray(
            np.column_stack([self.layers, texels_per_m, np.log2(texels_per_m)])
        )

    @cached_property
    def textures(self) -> tuple[F32, I64, I64]:
        """Mip-mapped texture atlas (data, offsets, sizes) of grass, gravel and brick, then the
        surface's two (surfaces.py)."""
        photos = [_photo("grass"), _photo("gravel"), _photo("brick")]
        return _pyramid_atlas(photos + self.surface_textures)

    # ------------------------------------------------------------------ queries
    @property
    def tmax_m(self) -> float:
        """Longest ray considered [m]."""
        return 4.0 * self.size_m

    def height(self, x_m: ArrayLike, y_m: ArrayLike) -> F64:
        """Ground height (positive up) [m] at north/east positions (N,), buildings excluded."""
        xs = np.atleast_1d(np.asarray(x_m, dtype=np.float64)).ravel()
        ys = np.atleast_1d(np.asarray(y_m, dtype=np.float64)).ravel()
        return np.asarray(
            _kernels.height_at(self.heights, 1.0 / self.res_m, self.x0, self.y0, xs, ys),
            dtype=np.float64,
        )

    def surface_height(self, x_m: ArrayLike, y_m: ArrayLike) -> F64:
        """Height of the top surface (ground or roof) [m] at (N,) positions."""
        xs = np.atleast_1d(np.asarray(x_m, dtype=np.float64)).ravel()
        ys = np.atleast_1d(np.asarray(y_m, dtype=np.float64)).ravel()
        h = self.height(xs, ys)
        for xmin, xmax, ymin, ymax, _, top in self.boxes:
            inside = (xs >= xmin) & (xs <= xmax) & (ys >= ymin) & (ys <= ymax)
            h = np.where(inside, np.maximum(h, top), h)
        return h

    def raycast(self, origins_world: ArrayLike, dirs_world: ArrayLike) -> RayHits:
        """Cast rays (N, 3) from origins (N, 3) (NED, metres); directions need not be unit."""
        o = np.ascontiguousarray(np.asarray(origins_world, dtype=np.float64).reshape(-1, 3))
        d = np.asarray(dirs_world, dtype=np.float64).reshape(-1, 3)
        if o.shape[0] == 1 and d.shape[0] > 1:
            o = np.ascontiguousarray(np.repeat(o, d.shape[0], axis=0))
        d = np.ascontiguousarray(d / np.linalg.norm(d, axis=1, keepdims=True))
        t, normals, kind, box = _kernels.cast_rays(o, d, self.kernel_geometry())
        pts = o + t[:, None] * d
        return RayHits(t, pts, normals, kind, box)

    def kernel_geometry(self) -> tuple[tuple[object, ...], tuple[object, ...]]:
        """The packed geometry every ray-casting kernel takes, (ground, boxes) (unpacked by
        _kernels._cast_ground and _kernels._cast_boxes)."""
        ground = (
            self.heights,
            1.0 / self.res_m,
            self.x0,
            self.y0,
            self.h_min,
            self.h_max,
            self.plane,
            self.lip_x,
            self.lip_y,
            self.blocks,
            self.b_inv,
            self.b_reach,
            self.tmax_m,
        )
        box_geo = (
            self.boxes,
            self.box_top,
            self.cell_start,
            self.cell_boxes,
            self.x0,
            self.y0,
            self.g_inv,
            self.g_nx,
            self.g_ny,
        )
        return ground, box_geo


# ---------------------------------------------------------------------------- terrains


def _hills(rng: np.random.Generator, size_m: float, res_m: float) -> F32:
    """Smooth irregular ground: three octaves of filtered noise, ~3-4 m of relief."""
    coarse_res = 1.0
    nc = int(round(size_m / coarse_res)) + 1
    h = (
        0.9 * _smooth_noise(rng, (nc, nc), 9.0)
        + 0.18 * _smooth_noise(rng, (nc, nc), 3.0)
        + 0.035 * _smooth_noise(rng, (nc, nc), 1.2)
    )
    n = int(round(size_m / res_m)) + 1
    fine = cv2.resize(h.astype(np.float32), (n, n), interpolation=cv2.INTER_CUBIC)
    # centre: h(0, 0) = 0
    c = (n - 1) // 2
    return np.asarray(fine - fine[c, c], dtype=np.float32)


def _slope(rng: np.random.Generator, size_m: float) -> tuple[F32, float]:
    """A tilted plane (exact in a bilinear 2x2 grid); returns heights and the cell size."""
    tilt = math.radians(rng.uniform(10.0, 15.0))
    azimuth = rng.uniform(0.0, 2 * math.pi)
    g = math.tan(tilt)
    half = size_m / 2.0
    xs = np.array([-half, half])
    X, Y = np.meshgrid(xs, xs)  # X varies along columns (x), Y along rows (y)
    H = g * (math.cos(azimuth) * X + math.sin(azimuth) * Y)
    return H.astype(np.float32), size_m


def _urban_boxes(rng: np.random.Generator, size_m: float) -> F64:
    """Buildings on a jittered 14 m lattice plus small boxes (cars, containers)."""
    boxes: list[tuple[float, ...]] = []
    half = size_m / 2.0 - 6.0
    spacing = 14.0
    centres = np.arange(-half, half + 1e-9, spacing)
    for cx in centres:
        for cy in centres:
            if rng.uniform() < 0.25:
                continue
            x = cx + rng.uniform(-3, 3)
            y = cy + rng.uniform(-3, 3)
            wx = rng.uniform(3.0, 8.0)
            wy = rng.uniform(3.0, 8.0)
            top = rng.uniform(1.0, 8.0)
            boxes.append((x - wx / 2, x + wx / 2, y - wy / 2, y + wy / 2, -1.0, top))
            if rng.uniform() < 0.5:  # a small box nearby
                sx = x + rng.choice([-1, 1]) * (wx / 2 + rng.uniform(1.5, 3.0))
                sy = y + rng.uniform(-2, 2)
                lx_, ly_ = rng.uniform(1.0, 2.5), rng.uniform(1.0, 4.5)
                boxes.append(
                    (
                        sx - lx_ / 2,
                        sx + lx_ / 2,
                        sy - ly_ / 2,
                        sy + ly_ / 2,
                        -1.0,
                        rng.uniform(1.0, 2.0),
                    )
                )
    arr = np.asarray(boxes, dtype=np.float64).reshape(-1, 6)
    # keep a clear take-off area around the origin
    cx_ = 0.5 * (arr[:, 0] + arr[:, 1])
    cy_ = 0.5 * (arr[:, 2] + arr[:, 3])
    rad = 0.5 * np.hypot(arr[:, 1] - arr[:, 0], arr[:, 3] - arr[:, 2])
    keep = np.hypot(cx_, cy_) - rad > 8.0
    return arr[keep]


def make_world(
    name: str,
    seed: int = 1,
    size_m: float = 160.0,
    res_m: float = 0.05,
    ground: GroundOptions | None = None,
) -> World:
    """Build a seeded terrain by name (flat, hills, urban, slope), its ground covered as
    ``ground`` says (surfaces.py; default: the photos, no patches)."""
    if name not in TERRAINS:
        raise SitlError(f"unknown terrain {name!r}; choose one of {', '.join(TERRAINS)}")
    rng = np.random.default_rng([seed, TERRAINS.index(name)])
    flat = np.zeros((2, 2), dtype=np.float32)
    no_boxes = np.zeros((0, 6))
    if name == "flat":
        return World(name, seed, size_m, flat, size_m, no_boxes, 6.0, ground)
    if name == "hills":
        h = _hills(rng, size_m, res_m)
        return World(name, seed, size_m, h, res_m, no_boxes, 6.0, ground)
    if name == "slope":
        h, cell = _slope(rng, size_m)
        return World(name, seed, size_m, h, cell, no_boxes, 6.0, ground)
    return World(name, seed, size_m, flat, size_m, _urban_boxes(rng, size_m), 12.0, ground)
