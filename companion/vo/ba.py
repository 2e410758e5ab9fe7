"""Local windowed bundle adjustment: Levenberg-Marquardt with the Schur complement.

Cameras are world-to-camera transforms T_cam_vo (K, 4, 4), perturbed on the left:
T <- exp(delta) T with delta = (rho, phi) (6,). Points X_vo (P, 3) are in the VO frame.
Observations are undistorted normalised coordinates; residuals are scaled by the focal length
so that the Huber threshold is in pixels (Triggs et al., "Bundle Adjustment - A Modern
Synthesis", 2000, sections 6 and 8; Hartley & Zisserman, appendix A6.3).

Each observation involves one camera, so the camera block of the normal equations is block
diagonal; eliminating the points (3x3 blocks) leaves a dense 6K x 6K system for the free
cameras.

Gravity prior (optional): the VO frame is gravity-aligned (its +z is down), so a camera's
gravity direction is g = R_cam_vo e_z; where the autopilot's attitude gives it as g_meas, a
residual w (g - g_meas) per free camera (3,) ties the window's roll and pitch to gravity. With
the left perturbation R <- exp(phi) R, dg/dphi = -[g]x. Without it, the roll/pitch of a
monocular map is only as good as the images make it: over a near-planar scene seen closely
(a take-off) the rotation-translation ambiguity lets it drift by degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.geometry import se3
from companion.types import F64

I64 = NDArray[np.int64]
B = NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class BaResult:
    """Optimised cameras (K, 4, 4), points (P, 3), per-observation residual norms [px] and
    the robust cost before/after."""

    T_cam_vo: F64
    points_vo: F64
    residual_px: F64
    cost_before: float
    cost_after: float
    iterations: int


def _skew_batch(v: F64) -> F64:
    """(N, 3) -> (N, 3, 3) cross-product matrices."""
    z = np.zeros(len(v))
    return np.stack(
        [
            np.stack([z, -v[:, 2], v[:, 1]], axis=1),
            np.stack([v[:, 2], z, -v[:, 0]], axis=1),
            np.stack([-v[:, 1], v[:, 0], z], axis=1),
        ],
        axis=1,
    )


def _accumulate(index: I64, values: F64, n: int) -> F64:
    """Sum values (M, ...) into n bins by index (M,): a fast np.add.at (bincount per entry)."""
    flat = values.reshape(len(values), -1)
    out = np.empty((n, flat.shape[1]))
    for k in range(flat.shape[1]):
        out[:, k] = np.bincount(index, weights=flat[:, k], minlength=n)
    return out.reshape((n, *values.shape[1:]))


def _pairs(obs_pt: I64, usable: NDArray[np.bool_], n_points: int) -> tuple[I64, I64]:
    """All ordered pairs (a, b) of usable observations that see the same point."""
    idx = np.flatnonzero(usable)
    order = idx[np.argsort(obs_pt[idx], kind="stable")]
    counts = np.bincount(obs_pt[order], minlength=n_points)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    c_of = counts[obs_pt[order]]  # group size of each sorted observation
    s_of = starts[obs_pt[order]]  # group start of each sorted observation
    a = np.repeat(np.arange(len(order)), c_of)
    offs = np.arange(len(a)) - np.repeat(np.cumsum(c_of) - c_of, c_of)
    b = np.repeat(s_of, c_of) + offs
    return order[a], order[b]


def residuals(
    T_cam_vo: F64, points_vo: F64, obs_cam: I64, obs_pt: I64, obs_xy: F64, focal_px: float
) -> tuple[F64, F64]:
    """Reprojection residuals (M, 2) [px] and the points in the cameras (M, 3)."""
    R = T_cam_vo[obs_cam, :3, :3]
    t = T_cam_vo[obs_cam, :3, 3]
    p_c = (R @ points_vo[obs_pt][:, :, None])[:, :, 0] + t
    z = p_c[:, 2:3]
    r = (p_c[:, :2] / z - obs_xy) * focal_px
    return r, p_c


def _robust_cost(r: F64, huber_px: float) -> float:
    n = np.linalg.norm(r, axis=1)
    quad = n <= huber_px
    return float(np.sum(np.where(quad, 0.5 * n**2, huber_px * (n - 0.5 * huber_px))))


@dataclass(frozen=True, slots=True)
class _Window:
    """The observations of one problem and the bookkeeping of its free cameras."""

    obs_cam: I64
    obs_pt: I64
    obs_xy: F64
    focal_px: float
    n_points: int
    free: I64  # indices of the free cameras
    free_index: I64  # (K,) position among the free cameras, -1 for fixed ones
    fo: I64  # (M,) free index of each observation's camera
    sel: B  # (M,) observation by a free camera
    pa: I64  # pairs of observations of the same point by free cameras (Schur complement)
    pb: I64

    @property
    def nf(self) -> int:
        return len(self.free)

    def residuals(self, T: F64, X: F64) -> tuple[F64, F64]:
        return residuals(T, X, self.obs_cam, self.obs_pt, self.obs_xy, self.focal_px)


def _window(
    obs_cam: I64, obs_pt: I64, obs_xy: F64, fixed_cams: B, focal_px: float, n_points: int
) -> _Window:
    free = np.flatnonzero(~fixed_cams)
    free_index = -np.ones(len(fixed_cams), dtype=np.int64)
    free_index[free] = np.arange(len(free))
    pa, pb = _pairs(obs_pt, free_index[obs_cam] >= 0, n_points)
    fo = free_index[obs_cam]
    return _Window(
        obs_cam, obs_pt, obs_xy, focal_px, n_points, free, free_index, fo, fo >= 0, pa, pb
    )


@dataclass(frozen=True, slots=True)
class _GravityPrior:
    """Measured gravity directions (G, 3) of the free cameras ``cams`` (G,) that have one."""

    cams: I64
    meas: F64
    weight: F64  # (G,)

    def residuals(self, T: F64) -> F64:
        """(G, 3) weighted gravity residuals of the free cameras with a measurement."""
        r = self.weight[:, None] * (T[self.cams, :3, 2] - self.meas)
        return np.asarray(r, dtype=np.float64)


def _gravity_prior(
    gravity_cam: F64 | None, gravity_weight: float | F64, fixed_cams: B
) -> _GravityPrior:
    g_meas = np.zeros((0, 3))
    g_free = np.zeros(0, dtype=np.int64)
    w_all = np.broadcast_to(np.asarray(gravity_weight, dtype=np.float64), fixed_cams.shape)
    if gravity_cam is not None:
        known = np.all(np.isfinite(gravity_cam), axis=1) & ~fixed_cams & (w_all > 0)
        g_free = np.flatnonzero(known)
        g_meas = gravity_cam[g_free]
    return _GravityPrior(g_free, g_meas, np.asarray(w_all[g_free], dtype=np.float64))


def _total_cost(r: F64, T: F64, huber_px: float, prior: _GravityPrior) -> float:
    return _robust_cost(r, huber_px) + 0.5 * float(np.sum(prior.residuals(T) ** 2))


@dataclass(frozen=True, slots=True)
class _State:
    """Cameras, points, their residuals and points in the cameras, and the cost."""

    T: F64
    X: F64
    r: F64
    p_c: F64
    cost: float


@dataclass(frozen=True, slots=True)
class _NormalEquations:
    """Point blocks Hpp (P, 3, 3) and gradient gp (P, 3); free-camera blocks Hcc (F, 6, 6) and
    gradient bc0 (F, 6); the per-observation camera-point blocks Hcp_o (M, 6, 3)."""

    Hpp: F64
    gp: F64
    Hcc: F64
    bc0: F64
    Hcp_o: F64


def _jacobians(T: F64, p_c: F64, obs_cam: I64, focal_px: float) -> tuple[F64, F64]:
    """Reprojection Jacobians w.r.t. the camera (M, 2, 6) and the point (M, 2, 3)."""
    z = p_c[:, 2]
    inv_z = 1.0 / z
    J_proj = np.zeros((len(z), 2, 3))
    J_proj[:, 0, 0] = focal_px * inv_z
    J_proj[:, 1, 1] = focal_px * inv_z
    J_proj[:, 0, 2] = -focal_px * p_c[:, 0] * inv_z**2
    J_proj[:, 1, 2] = -focal_px * p_c[:, 1] * inv_z**2
    J_cam = np.concatenate([J_proj, -J_proj @ _skew_batch(p_c)], axis=2)  # (M, 2, 6)
    J_pt = J_proj @ T[obs_cam, :3, :3]  # (M, 2, 3)
    return J_cam, J_pt


def _normal_equations(
    state: _State, win: _Window, prior: _GravityPrior, huber_px: float
) -> _NormalEquations:
    """Gauss-Newton normal equations with IRLS Huber weights and the gravity prior."""
    r = state.r
    n = np.linalg.norm(r, axis=1)
    w = np.where(n <= huber_px, 1.0, huber_px / np.maximum(n, 1e-12))  # IRLS Huber weights
    J_cam, J_pt = _jacobians(state.T, state.p_c, win.obs_cam, win.focal_px)
    wJc = J_cam * w[:, None, None]
    wJp = J_pt * w[:, None, None]
    wJcT = wJc.transpose(0, 2, 1)
    Hcc_o = wJcT @ J_cam
    Hcp_o = wJcT @ J_pt
    Hpp_o = wJp.transpose(0, 2, 1) @ J_pt
    gc_o = -(wJcT @ r[:, :, None])[:, :, 0]
    gp_o = -(wJp.transpose(0, 2, 1) @ r[:, :, None])[:, :, 0]
    Hpp = _accumulate(win.obs_pt, Hpp_o, win.n_points)
    gp = _accumulate(win.obs_pt, gp_o, win.n_points)
    sel, fo = win.sel, win.fo
    Hcc = _accumulate(fo[sel], Hcc_o[sel], win.nf)
    bc0 = _accumulate(fo[sel], gc_o[sel], win.nf)
    if len(prior.cams):  # J = w [0, -[g]x] on each free camera with a measurement
        g = state.T[prior.cams, :3, 2]
        Jg = np.zeros((len(prior.cams), 3, 6))
        Jg[:, :, 3:] = -prior.weight[:, None, None] * _skew_batch(g)
        rg = prior.residuals(state.T)
        Hcc[win.free_index[prior.cams]] += Jg.transpose(0, 2, 1) @ Jg
        bc0[win.free_index[prior.cams]] -= (Jg.transpose(0, 2, 1) @ rg[:, :, None])[:, :, 0]
    return _NormalEquations(Hpp, gp, Hcc, bc0, Hcp_o)


def _damped_point_inverse(Hpp: F64, lam: float) -> F64:
    """Inverses (P, 3, 3) of the Levenberg-Marquardt damped point blocks."""
    diag_p = np.einsum("pii->pi", Hpp)
    Hpp_d = Hpp + (lam * diag_p + 1e-9)[:, :, None] * np.eye(3)[None]
    return np.asarray(np.linalg.inv(Hpp_d), dtype=np.float64)


def _schur_solve(ne: _NormalEquations, Vinv: F64, lam: float, win: _Window) -> F64 | None:
    """Camera steps (F, 6) from the damped reduced camera system (the points eliminated);
    None when it is singular."""
    nf, fo, sel, obs_pt = win.nf, win.fo, win.sel, win.obs_pt
    if not nf:
        return np.zeros((0, 6))
    Y = ne.Hcp_o @ Vinv[obs_pt]  # (M, 6, 3)
    S_flat = np.zeros((nf * nf, 6, 6))
    if len(win.pa):
        blocks = Y[win.pa] @ ne.Hcp_o[win.pb].transpose(0, 2, 1)
        S_flat -= _accumulate(fo[win.pa] * nf + fo[win.pb], blocks, nf * nf)
    S = S_flat.reshape(nf, nf, 6, 6)
    for i in range(nf):
        S[i, i] += ne.Hcc[i] + lam * np.diag(np.diag(ne.Hcc[i])) + 1e-9 * np.eye(6)
    Yg = (Y[sel] @ ne.gp[obs_pt[sel]][:, :, None])[:, :, 0]
    bc = ne.bc0 - _accumulate(fo[sel], Yg, nf)
    Sm = S.transpose(0, 2, 1, 3).reshape(6 * nf, 6 * nf)
    try:
        return np.asarray(np.linalg.solve(Sm, bc.reshape(-1)).reshape(nf, 6), dtype=np.float64)
    except np.linalg.LinAlgError:
        return None


def _back_substitute(ne: _NormalEquations, Vinv: F64, dc: F64, win: _Window) -> F64:
    """Point steps (P, 3) given the camera steps."""
    rhs = ne.gp.copy()
    if win.nf:
        sel = win.sel
        back = (ne.Hcp_o[sel].transpose(0, 2, 1) @ dc[win.fo[sel]][:, :, None])[:, :, 0]
        rhs -= _accumulate(win.obs_pt[sel], back, win.n_points)
    return np.asarray((Vinv @ rhs[:, :, None])[:, :, 0], dtype=np.float64)


def _damped_step(
    state: _State,
    lam: float,
    ne: _NormalEquations,
    win: _Window,
    prior: _GravityPrior,
    huber_px: float,
) -> tuple[_State, float]:
    """Raise the damping until a step lowers the cost: the new state and the lowered damping;
    or the state unchanged and a damping over 1e6 (give up)."""
    while True:
        Vinv = _damped_point_inverse(ne.Hpp, lam)
        dc = _schur_solve(ne, Vinv, lam, win)
        if dc is None:
            lam *= 10
            if lam > 1e6:
                return state, lam
            continue
        dX = _back_substitute(ne, Vinv, dc, win)
        T_new = state.T.copy()
        for i, k in enumerate(win.free):
            T_new[k] = se3.exp(dc[i]) @ state.T[k]
        X_new = state.X + dX
        r_new, p_new = win.residuals(T_new, X_new)
        valid = np.all(p_new[:, 2] > 1e-6)
        cost_new = _total_cost(r_new, T_new, huber_px, prior) if valid else np.inf
        if cost_new < state.cost:
            return _State(T_new, X_new, r_new, p_new, cost_new), max(lam / 10, 1e-7)
        lam *= 10
        if lam > 1e6:
            return state, lam


class BundleAdjustment:
    """Refine cameras and points, one Levenberg-Marquardt iteration per :meth:`step` (a
    caller can spread them over the frames after a keyframe) or all of them in :meth:`run`:
    stepped or run, the iterations and their arithmetic are the same, and so is the result,
    to the bit. Cameras with ``fixed_cams`` True stay put (gauge and scale: fix at least two
    cameras of a monocular window).

    obs_cam, obs_pt: (M,) indices into the cameras (K, 4, 4) and points (P, 3); obs_xy: (M, 2)
    observations. gravity_cam: (K, 3) measured gravity direction in each camera frame (rows
    of NaN where unknown); gravity_weight: its residual's weight (pixel units per unit
    vector: a pixel sigma over the gravity direction's sigma in radians), one for all or
    (K,) per camera; 0 = no prior. The arrays are copied."""

    def __init__(
        self,
        T_cam_vo: F64,
        points_vo: F64,
        obs_cam: I64,
        obs_pt: I64,
        obs_xy: F64,
        fixed_cams: B,
        focal_px: float,
        huber_px: float = 2.0,
        iterations: int = 5,
        gravity_cam: F64 | None = None,
        gravity_weight: float | F64 = 0.0,
    ) -> None:
        self._win = _window(obs_cam, obs_pt, obs_xy, fixed_cams, focal_px, len(points_vo))
        self._prior = _gravity_prior(gravity_cam, gravity_weight, fixed_cams)
        self._huber_px = huber_px
        self._iterations = iterations
        T = T_cam_vo.copy()
        X = points_vo.copy()
        r, p_c = self._win.residuals(T, X)
        self._cost0 = _total_cost(r, T, huber_px, self._prior)
        self._state = _State(T, X, r, p_c, self._cost0)
        self._lam = 1e-4
        self.iterations_done = 0

    @property
    def done(self) -> bool:
        """Whether no iteration is left: all taken, or the damping gave up (over 1e6)."""
        return self.iterations_done >= self._iterations or self._lam > 1e6

    def step(self) -> bool:
        """One iteration (none when :attr:`done`); returns whether one is left after it."""
        if not self.done:
            self.iterations_done += 1
            ne = _normal_equations(self._state, self._win, self._prior, self._huber_px)
            self._state, self._lam = _damped_step(
                self._state, self._lam, ne, self._win, self._prior, self._huber_px
            )
        return not self.done

    def run(self) -> BaResult:
        """Every iteration left, then the result."""
        while self.step():
            pass
        return self.result()

    def result(self) -> BaResult:
        """The cameras and points as the iterations so far left them."""
        st = self._state
        residual_px = np.linalg.norm(st.r, axis=1)
        return BaResult(st.T, st.X, residual_px, self._cost0, st.cost, self.iterations_done)
