"""The scale methods, all fed the same per-frame input, and the metric trajectory.

Thesis methods: ``MSC`` (one sensor, the raw match at each keyframe), ``MSCwK`` (one sensor,
every frame, Kalman filter), ``M-MSC`` (every sensor at each keyframe, robust ML fusion).
Ours: ``M-MSCwK`` (the M-MSC fusion at every frame through the MSCwK filter), published by
default.
Baselines, named as in the thesis' comparisons:
- ``B7 window-ML``: Engel, Sturm & Cremers (IROS 2012) closed-form ML scale from pairs of VO
  and metric displacements over a sliding window; the metric displacement is the change of
  the height above ground measured by the range sensor (so it assumes level ground).
- ``B8 per-frame``: the range's depth at the laser pixel over the VO depth there, interpolated
  from the features around it, at every frame (Wu et al. 2014; Zhang et al. 2018).
- ``B9 plane``: the plane through the three map points closest to the laser pixel, intersected
  with the camera ray through it (Giubilato et al., IROS 2018).
Every method starts from the same initial scale: the first range's depth over the VO's median
depth; all restart when the VO re-initialises.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.scale import msc
from companion.scale.fusion import fuse
from companion.scale.kalman import ScaleKalman
from companion.scale.options import ScaleOptions
from companion.types import F64, ScaleEstimate, VoOutput

MATCH_WINDOW = 300  # attempts kept per sensor for the match rate (10 s at 30 Hz)
SWEEP_US = 1_000_000  # ReuseCounter forgets stale pairs this often


@dataclass(frozen=True, slots=True)
class ScaleInput:
    """What every method sees at a tracked frame.

    T_cam_vo (4, 4); lasers: sensor id -> (range [m], laser point in the camera frame (3,),
    range sigma [m]), ordered by sensor id; segment: VO map index (changes on re-init);
    prior: the scale and its sigma when the VO map started metric (on the ground plane:
    scale 1), else None (the first scale comes from the ranges, ``initial_scale``).
    """

    time_us: int
    vo: VoOutput
    T_cam_vo: F64
    lasers: dict[int, tuple[float, F64, float]]
    segment: int
    prior: tuple[float, float] | None = None  # (scale, sigma) known from the VO's start


def initial_scale(inp: ScaleInput) -> float | None:
    """First-range depth over the VO's median feature depth (before any match)."""
    f = inp.vo.features
    has = f.point_ids >= 0
    if not has.any() or not inp.lasers:
        return None
    z_vo = se3.transform(inp.T_cam_vo, f.points_vo[has])[:, 2]
    z_vo = z_vo[z_vo > 0]
    if len(z_vo) == 0:
        return None
    z_metric = float(np.mean([p[2] for _, p, _ in inp.lasers.values()]))
    return z_metric / float(np.median(z_vo))


@dataclass
class Method(ABC):
    """Base: state handling common to every method."""

    name: str
    camera: CameraModel
    opts: ScaleOptions
    scale: float | None = None
    sigma: float = float("nan")
    n_used: int = 0
    segment: int = -1
    # per sensor: did its MSC match succeed, over the last MATCH_WINDOW attempts (status)
    match_history: dict[int, deque[bool]] = field(default_factory=dict)
    # the frame's laser pixels by sensor id, projected once for all the sensors (_laser_uv)
    _uv_of: tuple[ScaleInput | None, dict[int, F64]] = field(
        default=(None, {}), repr=False, compare=False
    )

    def _laser_uv(self, inp: ScaleInput, sensor_id: int) -> F64:
        """(2,) the pixel of a sensor's laser point at this frame (NaN: not in the image): every
        sensor's projected in one call at the frame's first ask."""
        frame, uv_of = self._uv_of
        if frame is not inp:
            ids = list(inp.lasers)
            points = np.array([inp.lasers[i][1] for i in ids], dtype=np.float64)
            uv_of = dict(zip(ids, msc.laser_pixels(self.camera, points), strict=True))
            self._uv_of = (inp, uv_of)
        return uv_of[sensor_id]

    def first_laser_pixel(self, inp: ScaleInput) -> tuple[F64, F64] | None:
        """The first sensor's laser point (3,) [m, camera frame] and its pixel (2,), or None
        (no reading, or the point is outside the image)."""
        if not inp.lasers:
            return None
        _, p_cam, _ = inp.lasers[next(iter(inp.lasers))]
        uv = msc.laser_pixel(self.camera, p_cam)
        return None if uv is None else (p_cam, uv)

    def filter_state(self) -> tuple[float, int]:
        """(how long its scale filter has gated out every measurement [s], its restarts at
        them: companion/scale/kalman.py); (0, 0) for a method without a filter."""
        kf = getattr(self, "kf", None)
        if not isinstance(kf, ScaleKalman):
            return 0.0, 0
        return kf.outside_gate_s, kf.recoveries

    def match_rates(self) -> dict[int, float]:
        """Per sensor id: the share of recent frames with a reading whose MSC match (a
        consistent VO patch around the laser pixel) succeeded."""
        return {sid: sum(h) / len(h) for sid, h in sorted(self.match_history.items()) if h}

    def reset(self) -> None:
        self.scale = None
        self.sigma = float("nan")

    def step(self, inp: ScaleInput) -> ScaleEstimate | None:
        if inp.segment != self.segment:
            self.segment = inp.segment
            self.reset()
        if self.scale is None and inp.prior is not None:
            self._start(inp, *inp.prior)
        self.update(inp)
        if self.scale is None:
            s0 = initial_scale(inp)
            if s0 is not None:
                self._start(inp, s0, self.opts.init_sigma_rel * s0)
        if self.scale is None:
            return None
        return ScaleEstimate(inp.time_us, self.scale, self.sigma, self.name, self.n_used)

    @abstractmethod
    def update(self, inp: ScaleInput) -> None:
        """Fold one frame's measurements into ``scale``/``sigma`` (each method its own way)."""

    def _start(self, inp: ScaleInput, s0: float, sigma0: float) -> None:
        self.scale, self.sigma, self.n_used = s0, sigma0, 0
        self.on_initial(inp, s0, sigma0)

    def on_initial(self, inp: ScaleInput, s0: float, sigma0: float) -> None:  # noqa: B027
        """Hook: the initial scale was just set (nothing to do unless a method needs it)."""

    def _msc(self, inp: ScaleInput, sensor_id: int) -> msc.MscMeasurement | None:
        rng, p_cam, sig = inp.lasers[sensor_id]
        del rng
        m = msc.measure(
            sensor_id,
            inp.vo.features,
            inp.T_cam_vo,
            self.camera,
            p_cam,
            sig,
            self.opts.patch_half_px,
            self.opts.slope_factor,
            self.opts.edge_radius_px,
            self.opts.edge_depth_rel,
            self._laser_uv(inp, sensor_id),
        )
        history = self.match_history.setdefault(sensor_id, deque(maxlen=MATCH_WINDOW))
        history.append(m is not None)
        return m


@dataclass
class MSC(Method):
    """Raw MSC match of the first sensor at each keyframe, held in between."""

    def update(self, inp: ScaleInput) -> None:
        if not inp.vo.is_keyframe or not inp.lasers:
            return
        m = self._msc(inp, next(iter(inp.lasers)))
        if m is not None:
            self.scale, self.sigma, self.n_used = m.scale, m.sigma, 1


class ReuseCounter:
    """How often each (sensor, map point) pair has been matched lately.

    A sensor's beam stays on one map point for many frames (about 2 s in cruise at 3 m/s,
    for the whole of a hover or a descent): the MSC measurements those frames give share the
    point's depth error, so they are one measurement repeated, not independent ones. A
    Kalman filter that fuses them at the frame rate as independent is overconfident and
    follows one point's depth bias: in PX4 SIH's landings the points under the beams (near
    the focus of expansion, triangulated with little parallax) read 2-7 % deep, and the scale
    fell 3.5 % in 6 s while the VO's true unit held (docs/decisions.md, "Repeated MSC
    matches"). The n-th use of a pair within ``memory_us`` of its previous use counts with
    its sigma times sqrt(n), so one point's information grows like log(n), not n. A pair
    unused for ``memory_us`` is forgotten (swept once a second: the table holds the pairs of
    the last ``memory_us``, a few thousand at most). Landings replayed: a 2 s memory kept
    half the gain of 30 s (a hovering beam leaves its point and comes back to it)."""

    def __init__(self, memory_us: int) -> None:
        self.memory_us = memory_us
        self._uses: dict[tuple[int, int], tuple[int, int]] = {}  # pair -> (count, last time)
        self._swept_us: int | None = None

    def factors(self, time_us: int, pairs: list[tuple[int, int]]) -> F64:
        """sqrt(n) (len(pairs),) for these pairs used at ``time_us``, counting this use."""
        if self.memory_us <= 0:
            return np.ones(len(pairs))
        uses = self._uses
        if self._swept_us is None or abs(time_us - self._swept_us) >= SWEEP_US:
            self._swept_us = time_us
            for k in [k for k, (_, last) in uses.items() if time_us - last > self.memory_us]:
                del uses[k]
        n = np.empty(len(pairs))
        for i, pair in enumerate(pairs):
            prev = uses.get(pair)
            count = prev[0] + 1 if prev is not None and time_us - prev[1] <= self.memory_us else 1
            uses[pair] = (count, time_us)
            n[i] = count
        return np.sqrt(n)


@dataclass
class MSCwK(Method):
    """MSC of the first sensor at every frame through the scale Kalman filter (a match
    repeated on the same map point weighs less each time: ReuseCounter)."""

    kf: ScaleKalman | None = None
    sensors: str = "first"
    reuse: ReuseCounter | None = None

    def reset(self) -> None:
        super().reset()
        o = self.opts
        self.kf = ScaleKalman(
            o.random_walk_per_s, o.gate_chi2, o.gate_recover_s, o.gate_recover_spread
        )
        self.reuse = None  # a new map's points: counted afresh (_reuse)

    def _reuse(self) -> ReuseCounter:
        if self.reuse is None:
            self.reuse = ReuseCounter(int(self.opts.reuse_memory_s * 1e6))
        return self.reuse

    def on_initial(self, inp: ScaleInput, s0: float, sigma0: float) -> None:
        if self.kf is None:
            self.reset()
        assert self.kf is not None
        if not self.kf.initialized:
            self.kf.initialize(inp.time_us, s0, sigma0)

    def measurement(self, inp: ScaleInput) -> tuple[float, float, int] | None:
        if not inp.lasers:
            return None
        m = self._msc(inp, next(iter(inp.lasers)))
        if m is None:
            return None
        k = float(self._reuse().factors(inp.time_us, [(m.sensor_id, m.point_id)])[0])
        return m.scale, m.sigma * k, 1

    def update(self, inp: ScaleInput) -> None:
        if self.kf is None:
            self.reset()
        assert self.kf is not None
        z = self.measurement(inp)
        if z is None:
            return
        if not self.kf.initialized and self.scale is not None:
            self.kf.initialize(inp.time_us, self.scale, self.sigma)
        if self.kf.update(inp.time_us, z[0], z[1]):
            self.n_used = z[2]
        if self.kf.initialized:
            self.scale, self.sigma = self.kf.scale, self.kf.sigma


def _fused(
    method: Method, inp: ScaleInput, max_sensors: int, reuse: ReuseCounter | None = None
) -> tuple[float, float, int] | None:
    """Robust ML fusion of the MSC matches of the first ``max_sensors`` sensors (0 = all);
    with ``reuse``, each match's sigma grows with its map point's repeated use."""
    ids = list(inp.lasers)[:max_sensors] if max_sensors > 0 else list(inp.lasers)
    ms = [m for sid in ids if (m := method._msc(inp, sid)) is not None]
    if not ms:
        return None
    sigma = np.array([m.sigma for m in ms])
    if reuse is not None:
        sigma = sigma * reuse.factors(inp.time_us, [(m.sensor_id, m.point_id) for m in ms])
    res = fuse(np.array([m.scale for m in ms]), sigma, method.opts.fusion_outlier_sigmas)
    if res is None:
        return None
    return res[0], res[1], int(res[2].sum())


@dataclass
class MMSC(Method):
    """The thesis' M-MSC: at each keyframe, MSC on every sensor fused by robust maximum
    likelihood (no Kalman filter), held until the next keyframe; a keyframe where fewer than
    ``opts.mmsc_min_sensors`` matches survive the fusion's outlier test keeps the held value.
    ``max_sensors`` limits it to the first k sensors (the number-of-sensors study)."""

    max_sensors: int = 0

    def update(self, inp: ScaleInput) -> None:
        if not inp.vo.is_keyframe:
            return
        z = _fused(self, inp, self.max_sensors)
        # a lone match has no other sensor to be checked against (a bad map point or a beam
        # past an edge passes the fusion unseen): wait for agreeing sensors
        need = min(self.opts.mmsc_min_sensors, max(len(self.match_history), 1))
        if z is not None and z[2] >= need:
            self.scale, self.sigma, self.n_used = z


@dataclass
class MMSCwK(MSCwK):
    """Our extension: the M-MSC fusion at every frame, through the MSCwK Kalman filter."""

    def measurement(self, inp: ScaleInput) -> tuple[float, float, int] | None:
        return _fused(self, inp, 0, self._reuse())


@dataclass
class B7WindowML(Method):
    """Engel, Sturm & Cremers (IROS 2012): closed-form ML scale from x_i ~ N(lambda mu_i,
    sigma_x^2) (VO displacements) and y_i ~ N(mu_i, sigma_y^2) (metric ones):
    s_xx = sigma_y^2 sum x_i^2, s_yy = sigma_x^2 sum y_i^2, s_xy = sigma_y sigma_x sum x_i y_i,
    lambda = (s_xx - s_yy + sign(s_xy) sqrt((s_xx - s_yy)^2 + 4 s_xy^2))
             / (2 sigma_x^-1 sigma_y s_xy);
    here with 1D displacements along gravity (see the module docstring)."""

    history: deque[tuple[int, float, float]] = field(default_factory=lambda: deque(maxlen=4096))
    sigma_x: float = 0.01
    sigma_y: float = 0.02

    def reset(self) -> None:
        super().reset()
        self.history.clear()

    def update(self, inp: ScaleInput) -> None:
        if not inp.lasers:
            return
        R_vo_cam = inp.T_cam_vo[:3, :3].T
        c_vo = -R_vo_cam @ inp.T_cam_vo[:3, 3]
        # metric height above ground of the camera: the laser points' depth along gravity
        heights = [float((R_vo_cam @ p)[2]) for _, p, _ in inp.lasers.values()]
        self.history.append((inp.time_us, float(c_vo[2]), float(np.mean(heights))))
        t0 = inp.time_us - int(self.opts.b7_window_s * 1e6)
        while self.history and self.history[0][0] < t0:
            self.history.popleft()
        h = np.array(self.history)
        if len(h) < 10:
            return
        # pairs: consecutive samples at least b7_min_step_m of metric motion apart
        xs, ys = [], []
        last = 0
        for i in range(1, len(h)):
            dy = -(h[i, 2] - h[last, 2])  # height up = -(z down) in both
            dx = h[i, 1] - h[last, 1]
            if abs(dy) >= self.opts.b7_min_step_m:
                xs.append(dx)
                ys.append(dy)
                last = i
        if len(xs) < 3:
            return
        x = np.array(xs)  # VO displacements along gravity [VO units]
        y = np.array(ys)  # metric ones from the range-measured height [m]
        sx, sy = self.sigma_x, self.sigma_y
        s_xx = sy**2 * float(x @ x)
        s_yy = sx**2 * float(y @ y)
        s_xy = sy * sx * float(x @ y)
        if abs(s_xy) < 1e-12:
            return
        lam = (s_xx - s_yy + np.sign(s_xy) * np.sqrt((s_xx - s_yy) ** 2 + 4 * s_xy**2)) / (
            2 * sx**-1 * sy * s_xy
        )
        # Engel's lambda maps metric to visual units (x = lambda y): our scale is 1 / lambda
        if np.isfinite(lam) and lam > 0:
            self.scale, self.sigma, self.n_used = float(1.0 / lam), float(0.05 / lam), len(x)


@dataclass
class B8PerFrame(Method):
    """Laser depth over the VO depth at the laser pixel (inverse-distance interpolation of the
    features within the patch), first sensor, every frame."""

    def update(self, inp: ScaleInput) -> None:
        laser = self.first_laser_pixel(inp)
        f = inp.vo.features
        has = f.point_ids >= 0
        if laser is None or not has.any():
            return
        p_cam, uv = laser
        d = np.linalg.norm(f.pixels[has] - uv, axis=1)
        near = d <= self.opts.patch_half_px
        if not near.any():
            return
        z = se3.transform(inp.T_cam_vo, f.points_vo[has][near])[:, 2]
        w = 1.0 / np.maximum(d[near], 0.5)
        z_vo = float(np.sum(w * z) / np.sum(w))
        if z_vo > 0:
            self.scale, self.n_used = float(p_cam[2]) / z_vo, int(near.sum())


@dataclass
class B9Plane(Method):
    """Plane through the three map points nearest the laser pixel, intersected with the camera
    ray through that pixel; first sensor, every frame."""

    def update(self, inp: ScaleInput) -> None:
        laser = self.first_laser_pixel(inp)
        f = inp.vo.features
        has = np.flatnonzero(f.point_ids >= 0)
        if laser is None or len(has) < 3:
            return
        p_cam, uv = laser
        d = np.linalg.norm(f.pixels[has] - uv, axis=1)
        near = has[np.argsort(d)[:3]]
        if np.sort(d)[2] > 4 * self.opts.patch_half_px:
            return
        P = se3.transform(inp.T_cam_vo, f.points_vo[near])
        n = np.cross(P[1] - P[0], P[2] - P[0])
        if np.linalg.norm(n) < 1e-12:
            return
        ray = p_cam / np.linalg.norm(p_cam)
        denom = float(n @ ray)
        if abs(denom) < 1e-9:
            return
        t_vo = float(n @ P[0]) / denom
        if t_vo > 0:
            self.scale, self.n_used = float(np.linalg.norm(p_cam)) / t_vo, 3


def make_methods(
    camera: CameraModel, opts: ScaleOptions, sensor_study: int = 0
) -> dict[str, Method]:
    """One instance of every method, by name; with ``sensor_study`` = n, also M-MSC limited
    to the first 1..n sensors (named "M-MSC k=1" ...)."""
    study: dict[str, Method] = {
        f"M-MSC k={k}": MMSC(f"M-MSC k={k}", camera, opts, max_sensors=k)
        for k in range(1, sensor_study + 1)
    }
    return study | {
        "MSC": MSC("MSC", camera, opts),
        "MSCwK": MSCwK("MSCwK", camera, opts),
        "M-MSC": MMSC("M-MSC", camera, opts),
        "M-MSCwK": MMSCwK("M-MSCwK", camera, opts),
        "B7 window-ML": B7WindowML("B7 window-ML", camera, opts),
        "B8 per-frame": B8PerFrame("B8 per-frame", camera, opts),
        "B9 plane": B9Plane("B9 plane", camera, opts),
    }


class MetricTrajectory:
    """Applies a changing scale without position jumps: p += s_k * (p_vo_k - p_vo_{k-1}).

    Positions stay in the VO frame's orientation (metres); a VO re-initialisation continues
    from the last position and raises ``reset_counter``.
    """

    def __init__(self) -> None:
        self.position_m: F64 | None = None
        self._last_vo: F64 | None = None
        self._segment = -1
        self.reset_counter = 0

    def step(self, p_vo: F64, scale: float, segment: int) -> F64:
        if self.position_m is None or self._last_vo is None:
            self.position_m = scale * p_vo
        elif segment != self._segment:
            self.reset_counter += 1
        else:
            self.position_m = self.position_m + scale * (p_vo - self._last_vo)
        self._segment = segment
        self._last_vo = p_vo.copy()
        return self.position_m.copy()
