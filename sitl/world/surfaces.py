"""Hard grounds for any terrain: repeating and low-texture surfaces, water-like patches.

A surface is data the ray-casting renderer already reads (``_kernels.render``): the two ground
texture layers (a texture, its tile size [m] and rotation, an 8-bit tint) mixed with the weight
``fields[..., 0]`` and multiplied by the albedo field ``fields[..., 1]``; the domain warp
(``fields[..., 2:4]``) is zero, as laid floors are straight. A ground pixel's linear value is
``2 * albedo * shade * ((1 - w) * A * tint_A + w * B * tint_B)`` with A and B the two layers'
trilinear texture lookups in [0, 1]. The textures (square, 512 texels, wrapped) are drawn here:

- ``tiles``: 0.5 m tiles with 1.6 cm dark grout, every tile printed with the same speckle (the
  pattern repeats exactly every 0.5 m), plus a faint non-repeating wear layer;
- ``checkerboard``: black and white squares of ``checker_m`` (0.3 m by default; printed
  sheets on a lab floor: 0.03-0.1 m), a trace of dirt;
- ``checker_sheets``: the same squares printed on sheets of paper laid overlapping on a floor,
  as a lab's printed targets are: each sheet 8 x 6 squares in a white margin of a third of a
  square, its own phase and a turn of up to 4 deg, a printed label strip along one edge, a
  faint shadow at the edge of the sheet on top; 3 x 4 sheets in a texture that repeats every
  20 squares (1 m for 5 cm squares), so that no view over the floor sees one endless period;
- ``parking``: painted bay lines (2.5 m bays, 5 m deep, 12 cm lines) over asphalt: fine
  aggregate noise and low-frequency stains;
- ``concrete``: smooth concrete: low-contrast fine and mid-scale noise (a few 8-bit levels);
- ``carpet``: a uniform carpet: fibre noise finer than a pixel at flight height, averaged by the
  mip-mapping to a near-uniform colour with a trace of weave.

Water-like specular patches (``SpecularPatches``): seeded discs 1.5-4 m across, rasterised to a
0.1 m weight grid with soft edges, covering a given share of the world; their view-dependent
highlight is :mod:`companion.sitl.world.ground_effects`'s, their effect on the distance sensors
:mod:`companion.sitl.world.sensors`'s.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from companion.errors import SitlError
from companion.types import F64

F32 = NDArray[np.float32]

SURFACES = ("photo", "tiles", "checkerboard", "checker_sheets", "parking", "concrete", "carpet")
TEXTURE_SIZE = 512  # texels, as terrain.py's photos
FIRST_SURFACE_TEXTURE = 3  # the atlas holds grass, gravel, brick, then the surface's A and B
TILE_M = 0.5  # floor tile side [m]
CHECKER_M = 0.3  # checkerboard square side [m], by default
SHEETS_SPAN_SQUARES = 20  # checker_sheets: the texture's side in squares
SHEET_SQUARES = (8, 6)  # checker_sheets: a sheet's squares (along u, along v)
BAY_WIDTH_M = 2.5  # parking bay width [m]
_PATCH_CELL_M = 0.1  # specular weight grid [m]


def _noise(rng: np.random.Generator, sigma_texels: float, std: float, n: int = TEXTURE_SIZE) -> F64:
    """Wrapped Gaussian-filtered white noise (n, n), zero mean, standard deviation ``std``."""
    g = ndimage.gaussian_filter(rng.standard_normal((n, n)), sigma_texels, mode="wrap")
    g = g - g.mean()
    return np.asarray(std * g / (g.std() + 1e-12), dtype=np.float64)


def _soft(img: F64, sigma_texels: float) -> F64:
    """Anti-aliased edges: a wrapped Gaussian blur."""
    return np.asarray(ndimage.gaussian_filter(img, sigma_texels, mode="wrap"), dtype=np.float64)


def _tiles(rng: np.random.Generator) -> tuple[F64, F64]:
    """4 x 4 identical tiles with grout (A, tile 2 m) and a faint wear layer (B)."""
    per = TEXTURE_SIZE // 4
    speckle = 0.6 + _noise(rng, 1.2, 0.05, per)
    i = np.arange(per)
    grout_1d = (i < 2) | (i >= per - 2)  # 4 texels = 1.6 cm at 0.5 m / 128 texels
    grout = grout_1d[:, None] | grout_1d[None, :]
    tile = np.where(grout, 0.22, speckle)
    a = _soft(np.tile(tile, (4, 4)), 0.8)
    b = 0.5 + _noise(rng, 3.0, 0.08)
    return a, b


def _checkerboard(rng: np.random.Generator) -> tuple[F64, F64]:
    """8 x 8 squares (A, tile 8 squares: 2.4 m for 0.3 m squares) and dirt (B)."""
    per = TEXTURE_SIZE // 8
    k = np.arange(TEXTURE_SIZE) // per
    a = _soft(np.where((k[:, None] + k[None, :]) % 2 == 0, 0.88, 0.12), 0.7)
    b = 0.5 + _noise(rng, 2.0, 0.1)
    return a, b


def _checker_sheets(rng: np.random.Generator) -> tuple[F64, F64]:
    """Sheets of squares laid overlapping (A, tile SHEETS_SPAN_SQUARES squares) and dirt (B).

    3 x 4 sheets on a jittered grid, drawn one over the other in a random order; texel
    coordinates are in squares (the texture spans SHEETS_SPAN_SQUARES of them) and wrap, so
    that sheets cross the texture's edges seamlessly."""
    n = TEXTURE_SIZE
    per = n / SHEETS_SPAN_SQUARES  # texels per square
    c = (np.arange(n) + 0.5) / per  # texel centres [squares]
    u, v = np.meshgrid(c, c, indexing="xy")  # u along columns, v along rows
    span = float(SHEETS_SPAN_SQUARES)
    a = 0.30 + _noise(rng, 6.0, 0.03)  # the floor between the sheets: grey
    cols, rows = 3, 4
    pitch_u, pitch_v = span / cols, span / rows
    half_u = SHEET_SQUARES[0] / 2.0 + 1.0 / 3.0  # half a sheet with its margin [squares]
    half_v = SHEET_SQUARES[1] / 2.0 + 1.0 / 3.0
    order = rng.permutation(cols * rows)
    for k in order.tolist():
        i, j = divmod(k, rows)
        cu = (i + 0.5) * pitch_u + rng.uniform(-0.6, 0.6)
        cv = (j + 0.5) * pitch_v + rng.uniform(-0.6, 0.6)
        turn = np.radians(rng.uniform(-4.0, 4.0))
        du = (u - cu + span / 2.0) % span - span / 2.0  # wrapped offsets from the centre
        dv = (v - cv + span / 2.0) % span - span / 2.0
        lu = np.cos(turn) * du + np.sin(turn) * dv  # the sheet's own axes [squares]
        lv = -np.sin(turn) * du + np.cos(turn) * dv
        on = (np.abs(lu) <= half_u) & (np.abs(lv) <= half_v)
        shadow = (np.abs(lu) <= half_u + 0.08) & (np.abs(lv) <= half_v + 0.08) & ~on
        a = np.where(shadow, a * 0.7, a)
        pu, pv = lu + SHEET_SQUARES[0] / 2.0, lv + SHEET_SQUARES[1] / 2.0  # from its corner
        printed = (pu >= 0) & (pu < SHEET_SQUARES[0]) & (pv >= 0) & (pv < SHEET_SQUARES[1])
        phase = int(rng.integers(2))
        dark = (np.floor(pu).astype(np.int64) + np.floor(pv).astype(np.int64) + phase) % 2 == 1
        sheet = np.where(printed & dark, 0.12, 0.9)
        # a label strip in the margin along one long edge: short dark dashes
        label = (pv > -0.28) & (pv < -0.08) & (pu > 0.5) & (pu < SHEET_SQUARES[0] - 0.5)
        dashes = rng.random(64) < 0.55
        sheet = np.where(label & dashes[(np.floor(pu * 8.0).astype(np.int64)) % 64], 0.25, sheet)
        a = np.where(on, sheet, a)
    a = _soft(a, 0.7)
    b = 0.5 + _noise(rng, 2.0, 0.1)
    return a, b


def _parking(rng: np.random.Generator) -> tuple[F64, F64]:
    """Painted lines (A, tile 10 m: four 2.5 m bays in u, a 5 m row and a 5 m aisle in v) and
    asphalt (B, tile 1.5 m: aggregate of ~6 mm)."""
    n = TEXTURE_SIZE
    per_m = n / 10.0
    half_w = 0.06 * per_m  # 12 cm lines
    u = np.arange(n) + 0.5
    du = np.abs(((u / per_m + 0.5 * BAY_WIDTH_M) % BAY_WIDTH_M) - 0.5 * BAY_WIDTH_M) * per_m
    stall = (du <= half_w)[None, :] & ((u >= 0.3 * per_m) & (u <= 5.0 * per_m))[:, None]
    dv = np.abs(u - 5.0 * per_m)
    row_end = (dv <= half_w)[:, None] & np.ones((1, n), dtype=bool)
    a = _soft(np.where(stall | row_end, 1.0, 0.0), 0.8)
    b = 0.5 + _noise(rng, 2.0, 0.16)
    return a, b


def _concrete(rng: np.random.Generator) -> tuple[F64, F64]:
    """Fine pores (A, tile 2.3 m) and trowel marks (B, tile 3.7 m): a few levels of contrast."""
    return 0.5 + _noise(rng, 1.5, 0.035), 0.5 + _noise(rng, 8.0, 0.04)


def _carpet(rng: np.random.Generator) -> tuple[F64, F64]:
    """Fibres (A, tile 0.6 m: 1.2 mm texels, far below a pixel) and a faint weave (B)."""
    return 0.5 + _noise(rng, 0.6, 0.12), 0.5 + _noise(rng, 4.0, 0.025)


# per surface: drawing, (tile_m A, tile_m B), weight of B, tint A (b g r), tint B, albedo std
_DESIGNS = {
    "tiles": (_tiles, (4 * TILE_M, 1.73), 0.15, (150, 160, 172), (120, 125, 130), 0.02),
    "checkerboard": (
        _checkerboard,
        (8 * CHECKER_M, 1.9),
        0.05,
        (135, 135, 135),
        (90, 95, 100),
        0.01,
    ),
    "checker_sheets": (
        _checker_sheets,
        (SHEETS_SPAN_SQUARES * CHECKER_M, 1.9),
        0.05,
        (135, 135, 135),
        (90, 95, 100),
        0.01,
    ),
    "parking": (_parking, (10.0, 1.5), 0.5, (140, 145, 150), (140, 142, 146), 0.06),
    "concrete": (_concrete, (2.3, 3.7), 0.5, (152, 155, 158), (150, 152, 154), 0.04),
    "carpet": (_carpet, (0.6, 2.9), 0.5, (118, 92, 78), (118, 92, 78), 0.015),
}


def surface_ground(
    surface: str,
    seed: int,
    field_shape: tuple[int, int],
    field_res_m: float,
    checker_m: float = CHECKER_M,
) -> tuple[list[F32], F64, F64]:
    """The ground of ``surface`` (not ``photo``): its two textures (512, 512) float32 in [0, 1]
    (atlas ids FIRST_SURFACE_TEXTURE, +1), the two ground rows of the layer table (2, 9: tex,
    tile_m, cos, sin, off_u, off_v, tint b g r) and the fields (Ny, Nx, 4: weight of B, albedo,
    warp u, warp v) on terrain.py's field grid (cell ``field_res_m`` [m]); ``checker_m``: the
    square side [m] of ``checkerboard`` and ``checker_sheets``."""
    if surface not in _DESIGNS:
        raise SitlError(f"unknown surface {surface!r}; choose one of {', '.join(SURFACES)}")
    draw, (tile_a, tile_b), w_b, tint_a, tint_b, albedo_std = _DESIGNS[surface]
    if surface in ("checkerboard", "checker_sheets"):
        if not 0.0 < checker_m <= 2.0:
            raise SitlError(f"checker_m: a square side in (0, 2] m, got {checker_m}")
        tile_a = (8 if surface == "checkerboard" else SHEETS_SPAN_SQUARES) * checker_m
    rng = np.random.default_rng([seed, 808, SURFACES.index(surface)])
    a, b = draw(rng)
    textures = [np.clip(t, 0.0, 1.0).astype(np.float32) for t in (a, b)]
    off = rng.uniform(0, TEXTURE_SIZE, 2)
    angle_b = rng.uniform(0, 2 * math.pi)
    rows = np.array(
        [
            [FIRST_SURFACE_TEXTURE, tile_a, 1.0, 0.0, off[0], off[1], *tint_a],
            [
                FIRST_SURFACE_TEXTURE + 1,
                tile_b,
                math.cos(angle_b),
                math.sin(angle_b),
                0,
                0,
                *tint_b,
            ],
        ],
        dtype=np.float64,
    )
    stains = ndimage.gaussian_filter(rng.standard_normal(field_shape), 3.0 / field_res_m)
    stains = albedo_std * (stains - stains.mean()) / (stains.std() + 1e-12)
    fields = np.zeros((*field_shape, 4))
    fields[..., 0] = w_b
    fields[..., 1] = 1.0 + stains
    return textures, rows, fields


class SpecularPatches:
    """Water-like patches on the ground: a weight in [0, 1] per point (1 inside a patch, soft
    over ~0.2 m at its edge), on a grid of 0.1 m cells over the world's square."""

    def __init__(self, seed: int, size_m: float, share: float) -> None:
        if not 0.0 < share <= 0.5:
            raise SitlError(f"specular_patches: a share in (0, 0.5], got {share}")
        self.x0 = -size_m / 2.0
        self.inv_cell = 1.0 / _PATCH_CELL_M
        n = int(round(size_m / _PATCH_CELL_M))
        mask = np.zeros((n, n), dtype=bool)  # rows: y (east), cols: x (north)
        rng = np.random.default_rng([seed, 809])
        centres = []
        while mask.mean() < share:
            cx, cy = rng.uniform(self.x0 + 4, -self.x0 - 4, 2)
            r = rng.uniform(0.75, 2.0)
            centres.append((cx, cy, r))
            i0 = max(int((cy - r - self.x0) * self.inv_cell), 0)
            i1 = min(int((cy + r - self.x0) * self.inv_cell) + 2, n)
            j0 = max(int((cx - r - self.x0) * self.inv_cell), 0)
            j1 = min(int((cx + r - self.x0) * self.inv_cell) + 2, n)
            yy = self.x0 + (np.arange(i0, i1) + 0.5) * _PATCH_CELL_M
            xx = self.x0 + (np.arange(j0, j1) + 0.5) * _PATCH_CELL_M
            mask[i0:i1, j0:j1] |= (xx[None, :] - cx) ** 2 + (yy[:, None] - cy) ** 2 <= r * r
        self.discs = np.asarray(centres, dtype=np.float64).reshape(-1, 3)  # x, y, radius [m]
        soft = ndimage.gaussian_filter(mask.astype(np.float32), 1.0, mode="constant")
        self.grid = np.ascontiguousarray(soft, dtype=np.float32)

    def weight(self, x_m: ArrayLike, y_m: ArrayLike) -> F64:
        """Patch weight (N,) in [0, 1] at north/east positions (N,) [m] (bilinear)."""
        xs = np.atleast_1d(np.asarray(x_m, dtype=np.float64)).ravel()
        ys = np.atleast_1d(np.asarray(y_m, dtype=np.float64)).ravel()
        n = self.grid.shape[0]
        fx = np.clip((xs - self.x0) * self.inv_cell - 0.5, 0.0, n - 1.000001)
        fy = np.clip((ys - self.x0) * self.inv_cell - 0.5, 0.0, n - 1.000001)
        ix, iy = fx.astype(np.int64), fy.astype(np.int64)
        ax, ay = fx - ix, fy - iy
        g = self.grid
        top = g[iy, ix] * (1 - ax) + g[iy, ix + 1] * ax
        bottom = g[iy + 1, ix] * (1 - ax) + g[iy + 1, ix + 1] * ax
        return np.asarray(top * (1 - ay) + bottom * ay, dtype=np.float64)

    def bottom_depth_m(self, x_m: float, y_m: float) -> float:
        """Depth of the bottom under the surface at a point [m]: 0.2-0.8 m, seeded per patch
        (what a reading through the water finds)."""
        d2 = (self.discs[:, 0] - x_m) ** 2 + (self.discs[:, 1] - y_m) ** 2
        k = int(np.argmin(d2))
        return 0.2 + 0.6 * ((k * 0.6180339887) % 1.0)
