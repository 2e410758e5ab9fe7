"""Exact ray casting: hits lie on the surface, are the *first* hits, and match closed forms."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from companion.sitl.world.terrain import World

RNG = np.random.default_rng(7)


def bilinear_height(world: World, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Independent numpy reference of the terrain surface (bilinear in the height grid)."""
    H = world.heights.astype(np.float64)
    ny, nx = H.shape
    fx = np.clip((x - world.x0) / world.res_m, 0.0, nx - 1.000001)
    fy = np.clip((y - world.y0) / world.res_m, 0.0, ny - 1.000001)
    ix, iy = fx.astype(int), fy.astype(int)
    ax, ay = fx - ix, fy - iy
    return (H[iy, ix] * (1 - ax) + H[iy, ix + 1] * ax) * (1 - ay) + (
        H[iy + 1, ix] * (1 - ax) + H[iy + 1, ix + 1] * ax
    ) * ay


def box_hits(world: World, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Brute-force slab test of every box for every ray: nearest entry distance (inf = none)."""
    b = world.boxes
    if len(b) == 0:
        return np.full(len(o), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        lo = np.stack([b[:, 0], b[:, 2], -b[:, 5]], axis=1)  # (M, 3) in NED
        hi = np.stack([b[:, 1], b[:, 3], -b[:, 4]], axis=1)
        t1 = (lo[None] - o[:, None]) / d[:, None]
        t2 = (hi[None] - o[:, None]) / d[:, None]
        tnear = np.minimum(t1, t2).max(axis=2)
        tfar = np.maximum(t1, t2).min(axis=2)
    hit = (tnear <= tfar) & (tnear >= 0)
    return np.where(hit, tnear, np.inf).min(axis=1)


def random_camera_rays(n: int, height_m: float, world: World) -> tuple[np.ndarray, np.ndarray]:
    xy = RNG.uniform(-40, 40, (n, 2))
    ground = world.surface_height(xy[:, 0], xy[:, 1])
    o = np.column_stack([xy, -(ground + height_m)])
    d = np.column_stack([RNG.normal(0, 0.45, (n, 2)), np.ones(n)])
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("terrain", ["flat", "hills", "urban", "slope"])
def test_hits_lie_on_the_surface_and_are_first(
    terrain: str, world: Callable[[str, int], World]
) -> None:
    w = world(terrain, 1)
    o, d = random_camera_rays(400, 7.0, w)
    hits = w.raycast(o, d)
    assert np.isfinite(hits.t_m).all()
    ground_hit = hits.kind == 0
    p = hits.points_world
    # on the surface: the ground hits satisfy z = -h(x, y) to a micrometre
    gap = -p[ground_hit, 2] - bilinear_height(w, p[ground_hit, 0], p[ground_hit, 1])
    assert np.abs(gap).max() < 1e-6
    # first hit: nothing of the terrain is above the ray before t (2 mm steps)
    steps = np.linspace(0.0, 1.0, 3000)[None, :] * (hits.t_m[:, None] - 1e-4)
    pts = o[:, None, :] + steps[..., None] * d[:, None, :]
    above = -pts[..., 2] - bilinear_height(w, pts[..., 0].ravel(), pts[..., 1].ravel()).reshape(
        pts.shape[:2]
    )
    assert above.min() > 0.0
    # boxes: the nearest box entry agrees with a brute-force slab test over every box
    t_box = box_hits(w, o, d)
    t_ref = np.minimum(t_box, np.where(ground_hit, hits.t_m, np.inf))
    assert np.allclose(hits.t_m, t_ref, rtol=0, atol=1e-9)
    if terrain == "urban":
        assert (hits.kind == 1).any() and (hits.kind == 2).any()  # roofs and walls were hit
    # normals are unit and face the ray
    assert np.allclose(np.linalg.norm(hits.normals_world, axis=1), 1.0)
    assert (np.einsum("ij,ij->i", hits.normals_world, d) < 0).all()


@pytest.mark.parametrize("terrain", ["flat", "slope"])
def test_planes_match_closed_form(terrain: str, world: Callable[[str, int], World]) -> None:
    w = world(terrain, 3)
    o, d = random_camera_rays(300, 5.0, w)
    # plane through three surface points: n . p = c
    P = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0]], dtype=float)
    P[:, 2] = -w.height(P[:, 0], P[:, 1])
    n = np.cross(P[1] - P[0], P[2] - P[0])
    c = n @ P[0]
    t_ref = (c - o @ n) / (d @ n)
    assert np.abs(w.raycast(o, d).t_m - t_ref).max() < 1e-7
    if terrain == "slope":
        tilt = np.degrees(np.arccos(abs(n[2]) / np.linalg.norm(n)))
        assert 10.0 <= tilt <= 15.0


def test_terrains_have_their_character(world: Callable[[str, int], World]) -> None:
    hills = world("hills", 1)
    assert hills.res_m <= 0.05
    relief = hills.h_max - hills.h_min
    assert 2.0 < relief < 12.0
    urban = world("urban", 1)
    tops = urban.boxes[:, 5]
    assert len(tops) > 20 and tops.min() >= 1.0 and tops.max() <= 8.0
    # clear take-off area at the origin
    assert urban.surface_height([0.0], [0.0])[0] == 0.0
    assert world("flat", 1).h_max == 0.0


def test_same_seed_same_world_other_seed_other_world(world: Callable[[str, int], World]) -> None:
    from companion.sitl.world.terrain import make_world

    a = make_world("hills", 5)
    b = make_world("hills", 5)
    assert np.array_equal(a.heights, b.heights) and np.array_equal(a.fields, b.fields)
    assert not np.array_equal(a.heights, world("hills", 1).heights)
    assert not np.array_equal(make_world("urban", 5).boxes, world("urban", 1).boxes)
